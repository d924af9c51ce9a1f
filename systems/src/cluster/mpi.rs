//! The cluster's [`Transport`] over MPI (feature `mpi`, Open MPI through rsmpi): every
//! message is a byte vector to one rank of `MPI_COMM_WORLD`, received by probing, so
//! the waiting loops above keep their time limits.
//!
//! Sends block only until MPI has taken the message: the protocol's messages from rank
//! 0 are small (MPI sends them eagerly), and a worker's tiles go to a rank 0 that polls
//! for them every few milliseconds, so a send waits long only on a rank that is alive
//! but stuck; a rank that dies ends the whole run through `mpirun`. While it waits, MPI
//! spins on the worker's core (measured: a fifth of the core at interactive quality);
//! buffered sends only move the spinning to rank 0, whose receive then waits for the
//! worker's next MPI call. Non-blocking sends and receives, whose buffers must outlive
//! the call, would remove it.

use super::Transport;
use mpi::Threading;
use mpi::environment::Universe;
use mpi::topology::SimpleCommunicator;
use mpi::traits::*;

/// MPI started for this process: finalizes when dropped.
pub struct MpiSession {
    universe: Universe,
}

impl MpiSession {
    /// Starts MPI with threads allowed to call it one at a time (the schedule's systems
    /// run on bevy's threads); an error when MPI was started before or cannot give that.
    pub fn start() -> Result<MpiSession, String> {
        let (universe, threading) = mpi::initialize_with_threading(Threading::Serialized)
            .ok_or("MPI was already started")?;
        if threading < Threading::Serialized {
            return Err(format!(
                "this MPI library gives {threading:?} threading; Sylva needs Serialized or more"
            ));
        }
        Ok(MpiSession { universe })
    }

    /// This process's rank in `MPI_COMM_WORLD`.
    pub fn rank(&self) -> usize {
        self.universe.world().rank() as usize
    }

    /// Processes in `MPI_COMM_WORLD`.
    pub fn size(&self) -> usize {
        self.universe.world().size() as usize
    }

    /// The transport between this process and the others.
    pub fn transport(&self) -> MpiTransport {
        MpiTransport {
            rank: self.rank(),
            size: self.size(),
        }
    }

    /// Ends every process of the run now (`MPI_Abort`): after a failure, when a rank
    /// may be stuck and a regular finish would wait for it.
    pub fn abort(&self, code: i32) -> ! {
        self.universe.world().abort(code)
    }
}

/// Messages to and from the other ranks of `MPI_COMM_WORLD`.
pub struct MpiTransport {
    rank: usize,
    size: usize,
}

impl Transport for MpiTransport {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.size
    }

    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String> {
        if to >= self.size {
            return Err(format!("there is no rank {to}"));
        }
        SimpleCommunicator::world()
            .process_at_rank(to as i32)
            .send(bytes);
        Ok(())
    }

    fn try_receive(&self) -> Option<(usize, Vec<u8>)> {
        let probed = SimpleCommunicator::world()
            .any_process()
            .immediate_matched_probe()?;
        let from = probed.1.source_rank() as usize;
        let (bytes, _) = probed.matched_receive_vec::<u8>();
        Some((from, bytes))
    }
}
