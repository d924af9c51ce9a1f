//! What can end a cluster run ([`ClusterError`], each naming the rank and the phase) and
//! what a run counts ([`ClusterCounters`]).

use super::*;

/// Why a cluster run ended early.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ClusterError {
    /// A rank could not build the scene.
    LoadFailed {
        /// The rank.
        rank: usize,
        /// Its error.
        error: String,
    },
    /// A rank is about to render something else than rank 0.
    Mismatch {
        /// The rank.
        rank: usize,
        /// What differs.
        what: &'static str,
    },
    /// A rank sent nothing for longer than the time limit while rank 0 waited for it.
    Silent {
        /// The rank.
        rank: usize,
        /// How long it was silent.
        waited: Duration,
        /// Tiles it had been given and not returned.
        outstanding: usize,
    },
    /// A rank ended the run with an error of its own.
    Failed {
        /// The rank.
        rank: usize,
        /// Its error.
        error: String,
    },
    /// A message could not be read, or came when the protocol does not allow it.
    Protocol {
        /// Its sender.
        rank: usize,
        /// What was wrong.
        problem: String,
    },
    /// A message could not be sent.
    Send {
        /// The rank it was for.
        rank: usize,
        /// Why.
        reason: String,
    },
}

impl std::fmt::Display for ClusterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClusterError::LoadFailed { rank, error } => {
                write!(f, "rank {rank} could not build the scene: {error}")
            }
            ClusterError::Mismatch { rank, what } => write!(
                f,
                "rank {rank} would render a different {what} than rank 0: every rank must \
                 be given the same files and arguments (is a file different on its node?)"
            ),
            ClusterError::Silent {
                rank,
                waited,
                outstanding,
            } => write!(
                f,
                "rank {rank} sent nothing for {:.1} s ({outstanding} tiles outstanding): it \
                 died, hangs, or cannot reach rank 0",
                waited.as_secs_f64()
            ),
            ClusterError::Failed { rank, error } => write!(f, "rank {rank} failed: {error}"),
            ClusterError::Protocol { rank, problem } => {
                write!(f, "rank {rank} broke the protocol: {problem}")
            }
            ClusterError::Send { rank, reason } => {
                write!(f, "could not send to rank {rank}: {reason}")
            }
        }
    }
}

impl std::error::Error for ClusterError {}

/// What the cluster did in a frame (or, summed, in a run), as seen from this rank.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ClusterCounters {
    /// Frames shared out.
    pub frames: u64,
    /// Bytes this rank sent.
    pub bytes_sent: u64,
    /// Bytes this rank received.
    pub bytes_received: u64,
    /// Tiles this rank rendered.
    pub tiles_here: u64,
    /// Tiles other ranks rendered (counted on rank 0).
    pub tiles_elsewhere: u64,
    /// Of those, tiles rendered before rank 0 started their frame (pipelined).
    pub tiles_ahead: u64,
    /// Time this rank's threads had no tile to render while the frame was not done: on
    /// rank 0 from its last local tile to the last tile back, on a worker while it had
    /// none in hand.
    pub waited: Duration,
}

impl ClusterCounters {
    pub(super) fn add(&mut self, other: &ClusterCounters) {
        self.frames += other.frames;
        self.bytes_sent += other.bytes_sent;
        self.bytes_received += other.bytes_received;
        self.tiles_here += other.tiles_here;
        self.tiles_elsewhere += other.tiles_elsewhere;
        self.tiles_ahead += other.tiles_ahead;
        self.waited += other.waited;
    }
}
