//! Rank 0's side of a frame: tiles handed out in runs on demand, its own threads
//! rendering from the same counter, the workers' results gathered, silent or failed
//! ranks' tiles reclaimed.

use super::*;

/// What rank 0's thread serving the workers between frames holds: the transport, the
/// next job (opened ahead by the first worker ready for it) and what came for later.
pub(super) struct Desk {
    pub(super) transport: Arc<dyn Transport>,
    pub(super) size: usize,
    pub(super) timeout: Duration,
    pub(super) phase: u32,
    /// The job rank 0 starts next.
    pub(super) number: u64,
    pub(super) deferred: Vec<(usize, Message)>,
    pub(super) ahead: Option<Job>,
    pub(super) counters: ClusterCounters,
}

impl Desk {
    /// Serves until `halt` is set (the thread is unparked then); returns itself for
    /// rank 0 to take back, and the failure that ended it early, if one did.
    pub(super) fn serve(mut self, halt: &AtomicBool) -> (Desk, Result<(), ClusterError>) {
        let served = self.serve_until(halt);
        (self, served)
    }

    pub(super) fn serve_until(&mut self, halt: &AtomicBool) -> Result<(), ClusterError> {
        while !halt.load(Ordering::SeqCst) {
            while let Some((rank, message)) = receive_counted(&*self.transport, &mut self.counters)?
            {
                match message {
                    Message::Ready { phase, .. } if phase < self.phase => {}
                    Message::Ready { job, .. } | Message::Result { job, .. }
                        if job == self.number =>
                    {
                        let answer = serve_ahead(&mut self.ahead, job, self.size, rank, message)?;
                        if let Some(answer) = answer {
                            send_counted(&*self.transport, &mut self.counters, rank, &answer)?;
                        }
                    }
                    Message::Ready { job, .. } if job > self.number => {
                        self.deferred.push((rank, message));
                    }
                    // Tiles of a frame given up, answers to the stop that gave it up.
                    Message::Result { job, .. } if job < self.number => {}
                    Message::Halted { .. } => {}
                    Message::Fail { text } => {
                        return Err(ClusterError::Failed { rank, error: text });
                    }
                    other => return Err(unexpected(rank, &other)),
                }
            }
            if let Some(ahead) = &self.ahead {
                check_ahead_silence(ahead, self.timeout, Instant::now())?;
            }
            // Rank 0's threads are busy with its part between frames: look every few
            // milliseconds (workers hold runs in reserve).
            std::thread::park_timeout(POLL_BUSY);
        }
        Ok(())
    }
}

/// Rank 0's frame in progress: its job, its checks and its tiles.
pub(super) struct Lead<'a> {
    pub(super) job: Job,
    pub(super) checks: FrameChecks,
    pub(super) tiles: &'a [Tile],
}

/// Rank 0's view of one worker during a job.
#[derive(Clone, Copy, Debug)]
pub(super) struct WorkerState {
    /// Runs handed out and not yet back.
    pub(super) outstanding: usize,
    pub(super) done_sent: bool,
    pub(super) last_heard: Instant,
    /// Its checks, from its ready message for a job opened ahead (checked when rank 0
    /// starts the job).
    pub(super) checks: Option<FrameChecks>,
    /// Runs it asked for while ahead of rank 0 and has not been given.
    pub(super) waiting: u32,
}

impl Default for WorkerState {
    fn default() -> Self {
        Self {
            outstanding: 0,
            done_sent: false,
            last_heard: Instant::now(),
            checks: None,
            waiting: 0,
        }
    }
}

/// A worker's message for job `number`, the one after rank 0's current frame: a worker
/// ready for it opens it ahead of rank 0 and is handed runs at once; the tiles it
/// returns are kept until rank 0 starts the job and checks them. Returns the answer
/// to send the worker.
pub(super) fn serve_ahead(
    ahead: &mut Option<Job>,
    number: u64,
    size: usize,
    rank: usize,
    message: Message,
) -> Result<Option<Message>, ClusterError> {
    match message {
        Message::Ready {
            checks,
            tiles,
            want,
            ..
        } => {
            if tiles > MAX_TILES {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("it was ready for a frame of {tiles} tiles"),
                });
            }
            let job = ahead.get_or_insert_with(|| Job::new(number, tiles as usize, size));
            let worker = &mut job.workers[rank];
            worker.last_heard = Instant::now();
            worker.checks = Some(checks);
            if tiles as usize != job.tile_count {
                // Rank 0 tells which rank's frame differs from its own when it starts
                // the job; this one waits for that.
                worker.waiting = want;
                return Ok(None);
            }
            Ok(job.assign(rank, want))
        }
        Message::Result {
            first, tiles, want, ..
        } => {
            let Some(job) = ahead.as_mut() else {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("it returned tiles of job {number} before it had any"),
                });
            };
            job.workers[rank].last_heard = Instant::now();
            for (index, time) in job.take_run(rank, first, tiles)? {
                job.early.push((index, rank, time));
            }
            Ok(job.assign(rank, want))
        }
        other => Err(unexpected(rank, &other)),
    }
}

/// Gives up on a worker holding runs of the job opened ahead once it has been silent
/// longer than `timeout`.
pub(super) fn check_ahead_silence(
    ahead: &Job,
    timeout: Duration,
    now: Instant,
) -> Result<(), ClusterError> {
    for (rank, worker) in ahead.workers.iter().enumerate().skip(1) {
        let waited = now - worker.last_heard;
        if worker.outstanding > 0 && waited > timeout {
            return Err(ClusterError::Silent {
                rank,
                waited,
                outstanding: worker.outstanding,
            });
        }
    }
    Ok(())
}

/// Rank 0's thread serving the workers between frames.
pub(super) struct Away {
    pub(super) halt: Arc<AtomicBool>,
    pub(super) handle: std::thread::JoinHandle<(Desk, Result<(), ClusterError>)>,
}

/// The most tiles a worker's frame may have (a 32k × 32k image in 16-pixel tiles):
/// rank 0 sizes the next job from a worker's word before it can check it.
pub(super) const MAX_TILES: u32 = 1 << 22;

impl Cluster {
    /// Rank 0's side of a frame: its own threads take runs of tiles from the same
    /// counter the workers are served from. Ends early when the stop flag is set
    /// (Ctrl-C) or `cancel` is (the frame is given up on every rank).
    pub(super) fn lead(
        &mut self,
        pool: &rayon::ThreadPool,
        tiles: &[Tile],
        checks: FrameChecks,
        render: &TileRenderer,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Result<FrameEnd<Vec<TileResult>>, ClusterError> {
        let number = self.next_job;
        self.next_job += 1;
        let job = self.start_job(number, tiles, checks, on_tile)?;
        let next = job.next.clone();
        let runs = job.runs;
        let give_up = AtomicBool::new(false);
        let local_busy = AtomicUsize::new(pool.current_num_threads());
        let (sender, local) = mpsc::channel::<(usize, TileResult)>();
        let mut lead = Lead { job, checks, tiles };
        let outcome = pool.in_place_scope(|scope| {
            for _ in 0..pool.current_num_threads() {
                let sender = sender.clone();
                let (next, give_up, local_busy) = (&*next, &give_up, &local_busy);
                scope.spawn(move |_| {
                    'runs: loop {
                        let run = next.fetch_add(1, Ordering::Relaxed);
                        if run >= runs {
                            break;
                        }
                        for index in run_tiles(run, tiles.len()) {
                            if give_up.load(Ordering::Relaxed) {
                                break 'runs;
                            }
                            let start = Instant::now();
                            let result = render(tiles[index]);
                            on_tile(&tiles[index], start.elapsed());
                            if sender.send((index, result)).is_err() {
                                break 'runs;
                            }
                        }
                    }
                    local_busy.fetch_sub(1, Ordering::Release);
                });
            }
            drop(sender);
            let outcome = self.lead_loop(&mut lead, &local, &local_busy, on_tile, cancel);
            give_up.store(true, Ordering::Relaxed);
            outcome
        });
        Ok(match outcome? {
            FrameEnd::Done(()) => {
                let results = lead
                    .job
                    .results
                    .into_iter()
                    .map(|r| r.expect("every tile came back"));
                FrameEnd::Done(results.collect())
            }
            FrameEnd::Stopped => FrameEnd::Stopped,
            FrameEnd::Cancelled => FrameEnd::Cancelled,
        })
    }

    /// Rank 0's job `number`: the one workers opened ahead of it, once their checks
    /// equal rank 0's and their tiles are the frame's, or a new one.
    pub(super) fn start_job(
        &mut self,
        number: u64,
        tiles: &[Tile],
        checks: FrameChecks,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
    ) -> Result<Job, ClusterError> {
        let Some(mut job) = self.ahead.take().filter(|job| job.number == number) else {
            return Ok(Job::new(number, tiles.len(), self.size));
        };
        for (rank, worker) in job.workers.iter().enumerate() {
            if let Some(theirs) = worker.checks {
                compare_checks(rank, &checks, &theirs)?;
            }
        }
        if job.tile_count != tiles.len() {
            // Equal view checks mean equal grids; a count that differs is no renderer's.
            let rank = job.workers.iter().position(|w| w.checks.is_some());
            return Err(ClusterError::Protocol {
                rank: rank.unwrap_or(0),
                problem: format!(
                    "it was ready for {} tiles of a frame of {}",
                    job.tile_count,
                    tiles.len()
                ),
            });
        }
        for &(index, rank, time) in &job.early {
            if job.results[index].as_ref().map(|r| r.tile) != Some(tiles[index]) {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("tile {index} came back as another tile"),
                });
            }
            on_tile(&tiles[index], time);
        }
        self.last_frame.tiles_ahead += job.early.len() as u64;
        self.last_frame.tiles_elsewhere += job.early.len() as u64;
        job.early.clear();
        // A worker whose tile count differed from the first one's waited for the checks
        // (which, passed, mean equal frames).
        for rank in 1..self.size {
            let waiting = std::mem::take(&mut job.workers[rank].waiting);
            if waiting > 0
                && let Some(answer) = job.assign(rank, waiting)
            {
                self.send(rank, &answer)?;
            }
        }
        Ok(job)
    }

    /// Polls local results and messages until every tile is back and every worker has
    /// been told the frame is done, or the stop flag or `cancel` ends it first. A
    /// frame is given up only before any worker has been told it is done, so that
    /// every rank gives it up (a worker told so has already kept it, and may be on the
    /// next job).
    pub(super) fn lead_loop(
        &mut self,
        lead: &mut Lead,
        local: &mpsc::Receiver<(usize, TileResult)>,
        local_busy: &AtomicUsize,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Result<FrameEnd<()>, ClusterError> {
        let start = Instant::now();
        for state in &mut lead.job.workers {
            state.last_heard = start;
        }
        let mut pending = std::mem::take(&mut self.deferred);
        pending.reverse();
        let mut waiting_since: Option<Instant> = None;
        loop {
            let mut progressed = false;
            while let Ok((index, result)) = local.try_recv() {
                lead.job.results[index] = Some(result);
                lead.job.received += 1;
                self.last_frame.tiles_here += 1;
                progressed = true;
            }
            loop {
                let next = match pending.pop() {
                    Some(message) => Some(message),
                    None => self.receive()?,
                };
                let Some((rank, message)) = next else { break };
                progressed = true;
                self.lead_message(lead, rank, message, on_tile)?;
            }
            let job = &lead.job;
            let all_told = job.workers.iter().skip(1).all(|w| w.done_sent);
            if job.received == job.tile_count && all_told {
                if let Some(since) = waiting_since {
                    self.last_frame.waited += since.elapsed();
                }
                return Ok(FrameEnd::Done(()));
            }
            if self.stop.load(Ordering::SeqCst) {
                return Ok(FrameEnd::Stopped);
            }
            let none_told = job.workers.iter().all(|w| !w.done_sent);
            if none_told && cancel.is_some_and(|c| c.load(Ordering::SeqCst)) {
                self.end_phase()?;
                return Ok(FrameEnd::Cancelled);
            }
            if progressed {
                continue;
            }
            if local_busy.load(Ordering::Acquire) > 0 {
                // Rank 0's own threads are busy: look at the network every few
                // milliseconds, not at every tile they finish (a worker holds runs in
                // reserve, so it does not wait for the answer); each wake-up takes the
                // core from a render thread.
                std::thread::sleep(POLL_BUSY);
                continue;
            }
            waiting_since.get_or_insert_with(Instant::now);
            let now = Instant::now();
            for (rank, state) in lead.job.workers.iter().enumerate().skip(1) {
                if !state.done_sent {
                    self.check_silence(rank, now - state.last_heard, state.outstanding)?;
                }
            }
            if let Some(ahead) = &self.ahead {
                check_ahead_silence(ahead, self.timeout, now)?;
            }
            std::thread::sleep(POLL);
        }
    }

    /// Rank 0 handles one worker's message during a frame: of the frame, of the next
    /// one (opened ahead), or of a later one (kept for then).
    pub(super) fn lead_message(
        &mut self,
        lead: &mut Lead,
        rank: usize,
        message: Message,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
    ) -> Result<(), ClusterError> {
        lead.job.workers[rank].last_heard = Instant::now();
        let current = lead.job.number;
        match message {
            // A worker's ready message of a phase rank 0 has ended: it was waiting for
            // a frame that never came, and asks again in the new phase.
            Message::Ready { phase, .. } if phase < self.phase => {}
            // The next frame: opened ahead when frames follow (else a ready message is
            // kept for it), its tiles kept for it.
            Message::Ready { job, .. } | Message::Result { job, .. }
                if job == current + 1
                    && (self.frames_follow || matches!(message, Message::Result { .. })) =>
            {
                if let Some(answer) = serve_ahead(&mut self.ahead, job, self.size, rank, message)? {
                    self.send(rank, &answer)?;
                }
            }
            Message::Ready { job, .. } if job > current => {
                self.deferred.push((rank, message));
            }
            Message::Ready {
                job, checks, want, ..
            } if job == current => {
                compare_checks(rank, &lead.checks, &checks)?;
                self.assign(lead, rank, want)?;
            }
            // Tiles of a frame given up: sent before the worker heard so.
            Message::Result { job, .. } if job < current => {}
            Message::Result {
                job,
                first,
                tiles,
                want,
            } if job == current => {
                let taken = lead.job.take_run(rank, first, tiles)?;
                for (index, time) in taken {
                    let result = lead.job.results[index].as_ref();
                    if result.map(|r| r.tile) != Some(lead.tiles[index]) {
                        return Err(ClusterError::Protocol {
                            rank,
                            problem: format!("tile {index} came back as another tile"),
                        });
                    }
                    on_tile(&lead.tiles[index], time);
                    self.last_frame.tiles_elsewhere += 1;
                }
                self.assign(lead, rank, want)?;
            }
            // A worker's answer to a stop that gave a frame up.
            Message::Halted { .. } => {}
            Message::Fail { text } => return Err(ClusterError::Failed { rank, error: text }),
            other => return Err(unexpected(rank, &other)),
        }
        Ok(())
    }

    /// Gives `rank` up to `want` more runs of the frame, or tells it the frame is done.
    pub(super) fn assign(
        &mut self,
        lead: &mut Lead,
        rank: usize,
        want: u32,
    ) -> Result<(), ClusterError> {
        match lead.job.assign(rank, want) {
            Some(answer) => self.send(rank, &answer),
            None => Ok(()),
        }
    }

    /// Rank 0, its frame done, hands the transport to a thread that keeps serving the
    /// workers until rank 0 next needs it ([`reclaim`](Self::reclaim)): a worker ready
    /// for the next frame is given runs of it at once.
    pub(super) fn dispatch_until_next_frame(&mut self) {
        if self.size < 2
            || !self.frames_follow
            || self.away.is_some()
            || self.stop.load(Ordering::SeqCst)
        {
            return;
        }
        let desk = Desk {
            transport: self.transport.clone(),
            size: self.size,
            timeout: self.timeout,
            phase: self.phase,
            number: self.next_job,
            deferred: std::mem::take(&mut self.deferred),
            ahead: self.ahead.take(),
            counters: ClusterCounters::default(),
        };
        let halt = Arc::new(AtomicBool::new(false));
        let halted = halt.clone();
        let spawned = std::thread::Builder::new()
            .name("sylva-cluster-desk".into())
            .spawn(move || desk.serve(&halted));
        // Without a thread to spare the workers wait for rank 0's next frame, as
        // without pipelining (the desk went down with the failed spawn).
        if let Ok(handle) = spawned {
            self.away = Some(Away { halt, handle });
        }
    }

    /// Takes the transport back from the thread serving the workers between frames,
    /// with the next job it opened ahead and what else it received. Its failure ends
    /// the run: the other ranks are told, and it is returned.
    pub(super) fn reclaim(&mut self) -> Result<(), ClusterError> {
        let Some(away) = self.away.take() else {
            return Ok(());
        };
        away.halt.store(true, Ordering::SeqCst);
        away.handle.thread().unpark();
        let (desk, served) = match away.handle.join() {
            Ok(returned) => returned,
            Err(_) => {
                let error = ClusterError::Failed {
                    rank: self.rank,
                    error: "rank 0's thread serving the workers between frames panicked".into(),
                };
                return Err(self.fail_run(error));
            }
        };
        self.deferred = desk.deferred;
        self.ahead = desk.ahead;
        self.carried.add(&desk.counters);
        served.map_err(|error| self.fail_run(error))
    }

    /// Ends the run on `error`: the other ranks are told, the stop flag set.
    pub(super) fn fail_run(&mut self, error: ClusterError) -> ClusterError {
        self.abandon(&error.to_string());
        self.failure = Some(error.clone());
        self.stop.store(true, Ordering::SeqCst);
        error
    }
}
