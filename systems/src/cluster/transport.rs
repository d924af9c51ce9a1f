//! How ranks talk: the [`Transport`] trait (MPI's or channels'), in-process channels
//! ([`ChannelTransport`], threads as ranks), and sends and receives that count bytes.

use super::*;

/// Moves messages between the ranks of a cluster run.
pub trait Transport: Send + Sync {
    /// This process's rank, `0..size`; rank 0 leads.
    fn rank(&self) -> usize;
    /// Ranks in the run.
    fn size(&self) -> usize;
    /// Sends `bytes` to rank `to`; an error says why it could not be delivered.
    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String>;
    /// A message that has arrived and its sender, without waiting.
    fn try_receive(&self) -> Option<(usize, Vec<u8>)>;
}

/// Sends `message` to rank `to`, counting its bytes.
pub(super) fn send_counted(
    transport: &dyn Transport,
    counters: &mut ClusterCounters,
    to: usize,
    message: &Message,
) -> Result<(), ClusterError> {
    let bytes = message.encode();
    counters.bytes_sent += bytes.len() as u64;
    transport
        .send(to, &bytes)
        .map_err(|reason| ClusterError::Send { rank: to, reason })
}

/// A message that has arrived and its sender, its bytes counted.
pub(super) fn receive_counted(
    transport: &dyn Transport,
    counters: &mut ClusterCounters,
) -> Result<Option<(usize, Message)>, ClusterError> {
    let Some((rank, bytes)) = transport.try_receive() else {
        return Ok(None);
    };
    counters.bytes_received += bytes.len() as u64;
    match Message::decode(&bytes) {
        Ok(message) => Ok(Some((rank, message))),
        Err(wire::Malformed) => Err(ClusterError::Protocol {
            rank,
            problem: format!("a message of {} bytes could not be read", bytes.len()),
        }),
    }
}

/// Ranks as threads of one process, joined by channels: the protocol without MPI. As
/// with MPI, a message to a rank whose thread has ended is delivered and never read,
/// and (with [`mesh_with_eager_limit`](Self::mesh_with_eager_limit)) a large message's
/// send waits until the rank takes it, as MPI's rendezvous sends do.
/// bevy's task pool is one per process, so each rank's schedule should run on the
/// single-threaded executor: blocked in `render_tiles` waiting for each other, ranks
/// would otherwise hold all of the pool's threads.
pub struct ChannelTransport {
    rank: usize,
    eager_limit: usize,
    senders: Vec<mpsc::Sender<Envelope>>,
    receivers: Arc<Vec<Mutex<mpsc::Receiver<Envelope>>>>,
}

/// A message's bytes, the rank that sent them, and the sender waiting for it to be
/// taken (a rendezvous send).
pub(super) type Envelope = (usize, Vec<u8>, Option<mpsc::SyncSender<()>>);

impl ChannelTransport {
    /// `size` transports that reach each other, one per rank; every send returns at
    /// once.
    pub fn mesh(size: usize) -> Vec<ChannelTransport> {
        Self::mesh_with_eager_limit(size, usize::MAX)
    }

    /// [`mesh`](Self::mesh) whose sends of more than `eager_limit` bytes wait until the
    /// receiving rank takes the message (as MPI's large sends do).
    pub fn mesh_with_eager_limit(size: usize, eager_limit: usize) -> Vec<ChannelTransport> {
        let (senders, receivers): (Vec<_>, Vec<_>) = (0..size).map(|_| mpsc::channel()).unzip();
        let receivers = Arc::new(receivers.into_iter().map(Mutex::new).collect::<Vec<_>>());
        (0..size)
            .map(|rank| ChannelTransport {
                rank,
                eager_limit,
                senders: senders.clone(),
                receivers: receivers.clone(),
            })
            .collect()
    }
}

impl Transport for ChannelTransport {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.senders.len()
    }

    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String> {
        let sender = self
            .senders
            .get(to)
            .ok_or_else(|| format!("there is no rank {to}"))?;
        let (taken, wait) = match bytes.len() > self.eager_limit {
            true => {
                let (taken, wait) = mpsc::sync_channel(1);
                (Some(taken), Some(wait))
            }
            false => (None, None),
        };
        sender
            .send((self.rank, bytes.to_vec(), taken))
            .map_err(|_| "the rank has ended".to_owned())?;
        if let Some(wait) = wait {
            wait.recv().map_err(|_| "the rank has ended".to_owned())?;
        }
        Ok(())
    }

    fn try_receive(&self) -> Option<(usize, Vec<u8>)> {
        let (rank, bytes, taken) = self.receivers[self.rank].lock().ok()?.try_recv().ok()?;
        if let Some(taken) = taken {
            let _ = taken.send(());
        }
        Some((rank, bytes))
    }
}
