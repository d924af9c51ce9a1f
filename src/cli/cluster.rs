//! This process's place in a run: alone, or (built with the `mpi` feature and started
//! by an MPI launcher such as `mpirun`) one rank of a cluster run. The subcommands ask
//! it whether they lead (write images, print summaries), agree on the loaded scene
//! through it, and hand their world its `Cluster` resource; the protocol itself lives
//! in `sylva_systems::cluster`.

use anyhow::Result;
use clap::Args;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
#[cfg(feature = "mpi")]
use std::time::Duration;
use sylva::prelude::*;
use sylva::systems::cluster::{Cluster, ClusterCounters, ClusterError};

/// The cluster options of the subcommands that render.
#[derive(Args, Clone, Debug)]
pub(crate) struct ClusterArgs {
    #[cfg(feature = "mpi")]
    /// Under mpirun: the longest a rank waits for another before the run is ended with
    /// an error naming the silent rank.
    #[arg(long, value_name = "DURATION", default_value = "60s", value_parser = super::parse_duration)]
    cluster_timeout: Duration,
}

/// True when an MPI launcher started this process (Open MPI, MPICH/Hydra, PMIx).
#[cfg(feature = "mpi")]
fn launched_by_mpi() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK"]
        .iter()
        .any(|name| std::env::var_os(name).is_some())
}

/// This process alone, or a rank of an MPI run.
pub(crate) struct Node {
    #[cfg(feature = "mpi")]
    session: Option<sylva::systems::cluster::mpi::MpiSession>,
    #[cfg(feature = "mpi")]
    timeout: Duration,
    rank: usize,
    size: usize,
}

impl Node {
    /// Joins the MPI run this process was launched into, if any.
    pub(crate) fn join(args: &ClusterArgs) -> Result<Node> {
        #[cfg(feature = "mpi")]
        if launched_by_mpi() {
            use sylva::systems::cluster::mpi::MpiSession;
            let session = MpiSession::start().map_err(|e| anyhow::anyhow!("MPI: {e}"))?;
            return Ok(Node {
                rank: session.rank(),
                size: session.size(),
                session: Some(session),
                timeout: args.cluster_timeout,
            });
        }
        let _ = args;
        Ok(Node {
            #[cfg(feature = "mpi")]
            session: None,
            #[cfg(feature = "mpi")]
            timeout: args.cluster_timeout,
            rank: 0,
            size: 1,
        })
    }

    /// True on the process that writes images and prints: rank 0, or the only one.
    pub(crate) fn leads(&self) -> bool {
        self.rank == 0
    }

    /// True in a run of more than one process.
    pub(crate) fn is_cluster(&self) -> bool {
        self.size > 1
    }

    /// True when an MPI launcher started this process (a run of one rank included).
    #[cfg(feature = "view")]
    pub(crate) fn launched_by_mpi(&self) -> bool {
        #[cfg(feature = "mpi")]
        return self.session.is_some();
        #[cfg(not(feature = "mpi"))]
        false
    }

    /// Where this rank writes the Chrome trace asked for as `path`: rank 0 there, rank
    /// r beside it as `NAME.rank<r>.json`.
    pub(crate) fn trace_path(&self, path: Option<&Path>) -> Option<PathBuf> {
        let path = path?;
        if self.rank == 0 {
            return Some(path.to_owned());
        }
        let stem = path
            .file_stem()
            .map_or("trace".into(), |s| s.to_string_lossy().into_owned());
        Some(path.with_file_name(format!("{stem}.rank{}.json", self.rank)))
    }

    /// Every rank reports whether it loaded the scene; each returns its world only when
    /// all did. A failure ends the run: rank 0 prints which rank failed and why. Then
    /// Ctrl-C (SIGINT, or SIGTERM from `mpirun`) on the leading process sets the flag
    /// returned, which the cluster's frames also stop on; a worker stops when rank 0
    /// says so (or at a second signal).
    pub(crate) fn agree<T>(
        &mut self,
        loaded: Result<T>,
    ) -> Result<(T, Option<Cluster>, Arc<AtomicBool>)> {
        let (loaded, cluster) = self.agree_loaded(loaded)?;
        let interrupt = match &cluster {
            // A worker keeps serving through the first signal: `mpirun` signals every
            // rank, and a worker gone in the middle of sending a tile can take rank 0
            // down before it has written what it has. Rank 0's stop ends it.
            Some(cluster) if cluster.leads() => super::watch_interrupts(cluster.stop_flag()),
            _ => super::interrupt_flag(),
        };
        Ok((loaded, cluster, interrupt))
    }

    /// [`agree`](Self::agree) without the signal handling: Ctrl-C keeps its default
    /// action (the window's case, as without a cluster).
    pub(crate) fn agree_loaded<T>(&mut self, loaded: Result<T>) -> Result<(T, Option<Cluster>)> {
        #[cfg(feature = "mpi")]
        if let Some(session) = &self.session {
            let mut cluster = Cluster::new(
                Box::new(session.transport()),
                self.timeout,
                Arc::new(AtomicBool::new(false)),
            );
            let (loaded, report) = match loaded {
                Ok(value) => (Some(value), Ok(())),
                Err(error) => (None, Err(format!("{error:#}"))),
            };
            if let Err(error) = cluster.agree_loaded(report) {
                self.fail_with(&error);
            }
            let loaded = loaded.expect("a rank that failed to load heard a failure");
            return Ok((loaded, Some(cluster)));
        }
        Ok((loaded?, None))
    }

    /// When a worker's progressive driver stops: only when rank 0 says so (the leader
    /// keeps its own conditions).
    pub(crate) fn stop_at(&self, leader: StopAt, world: &World) -> StopAt {
        match world.get_resource::<Cluster>() {
            Some(cluster) if !cluster.leads() => StopAt {
                frames: Some(u32::MAX),
                interrupt: Some(cluster.stop_flag()),
                ..StopAt::default()
            },
            _ => leader,
        }
    }

    /// Rank 0 ends the run's frames: the workers leave their loops. Returns the
    /// cluster's failure, if the run failed instead.
    pub(crate) fn end_frames(&self, world: &mut World) -> Option<String> {
        let mut cluster = world.get_resource_mut::<Cluster>()?;
        if let Some(failure) = cluster.failure() {
            return Some(failure.to_string());
        }
        if let Err(error) = cluster.finish() {
            return Some(error.to_string());
        }
        None
    }

    /// Ends a failed run: rank 0 prints the error and stops every rank; a worker prints
    /// its error and waits for rank 0 to stop it (leaving on its own could end the run
    /// before rank 0 has written what it has), for at most the time limit.
    pub(crate) fn fail(&self, error: &str) -> ! {
        match self.leads() {
            true => eprintln!("error: {error}"),
            false => eprintln!("error: rank {}: {error}", self.rank),
        }
        self.stop_all()
    }

    /// [`fail`](Self::fail) for the cluster's own errors: a worker told by rank 0 that
    /// the run failed leaves the telling to rank 0, so each error is printed once.
    pub(crate) fn fail_with(&self, error: &ClusterError) -> ! {
        match error {
            ClusterError::Failed { rank: 0, .. } if !self.leads() => self.stop_all(),
            error => self.fail(&error.to_string()),
        }
    }

    /// Stops every rank (a worker first waits for rank 0 to do it) and exits with 1.
    fn stop_all(&self) -> ! {
        #[cfg(feature = "mpi")]
        if let Some(session) = &self.session {
            if !self.leads() {
                std::thread::sleep(self.timeout);
            }
            session.abort(1);
        }
        std::process::exit(1)
    }

    /// Passes a subcommand's result on; an error in a cluster run ends every rank
    /// ([`fail`](Self::fail)) instead of waiting in MPI's finish for ranks still busy.
    pub(crate) fn end<T>(&self, result: Result<T>) -> Result<T> {
        match result {
            Err(error) if self.is_cluster() => self.fail(&format!("{error:#}")),
            result => result,
        }
    }

    /// The summary line of what the cluster did, on rank 0 of a cluster run.
    pub(crate) fn summary(&self, world: &World) -> Option<String> {
        let cluster = world.get_resource::<Cluster>()?;
        if !self.is_cluster() {
            return None;
        }
        Some(counters_line(self.size, &cluster.total))
    }
}

/// `cluster: 3 ranks, …` from rank 0's counters.
fn counters_line(ranks: usize, total: &ClusterCounters) -> String {
    let frames = total.frames.max(1) as f64;
    let tiles = (total.tiles_here + total.tiles_elsewhere).max(1) as f64;
    format!(
        "  cluster: {ranks} ranks, {:.0} % of the tiles rendered by the other ranks ({:.0} % of those ahead of rank 0's frame), {:.2} MB received and {:.3} MB sent per frame, rank 0 waited {:.1} ms per frame for the last tiles",
        100.0 * total.tiles_elsewhere as f64 / tiles,
        100.0 * total.tiles_ahead as f64 / total.tiles_elsewhere.max(1) as f64,
        total.bytes_received as f64 / frames / 1e6,
        total.bytes_sent as f64 / frames / 1e6,
        total.waited.as_secs_f64() * 1e3 / frames,
    )
}
