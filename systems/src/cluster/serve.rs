//! A worker's side of a frame: say it is ready, render what rank 0 hands out, return
//! each run of tiles, and serve the next frame's first run ahead.

use super::*;

impl Cluster {
    /// A worker's side of a frame: say it is ready, render what rank 0 hands out,
    /// return each run of tiles as it finishes. `None` when rank 0 ended the run
    /// instead.
    pub(super) fn serve(
        &mut self,
        pool: &rayon::ThreadPool,
        tiles: &[Tile],
        checks: FrameChecks,
        render: &TileRenderer,
    ) -> Result<Option<Vec<TileResult>>, ClusterError> {
        let job = self.next_job;
        self.next_job += 1;
        let threads = pool.current_num_threads();
        self.send(
            0,
            &Message::Ready {
                phase: self.phase,
                job,
                checks,
                tiles: tiles.len() as u32,
                want: threads as u32 + RESERVE_RUNS,
            },
        )?;
        type Run = (usize, Vec<(u64, TileResult)>);
        let (sender, local) = mpsc::channel::<Run>();
        let mut mine = Vec::new();
        let give_up = AtomicBool::new(false);
        let give_up = &give_up;
        pool.in_place_scope(|scope| {
            let mut in_flight = 0usize;
            let mut done = false;
            let mut last_heard = Instant::now();
            let mut idle_since: Option<Instant> = Some(Instant::now());
            let mut finished: Option<Run> = None;
            loop {
                let mut progressed = false;
                while let Some((rank, message)) = self.receive()? {
                    progressed = true;
                    last_heard = Instant::now();
                    match message {
                        Message::Tiles { job: j, runs } if j == job && rank == 0 => {
                            for (first, count) in runs {
                                let (first, count) = (first as usize, count as usize);
                                let Some(run) = tiles.get(first..first.saturating_add(count))
                                else {
                                    return Err(ClusterError::Protocol {
                                        rank,
                                        problem: format!(
                                            "tiles {first}..{} are not in the frame",
                                            first.saturating_add(count)
                                        ),
                                    });
                                };
                                in_flight += 1;
                                let sender = sender.clone();
                                scope.spawn(move |_| {
                                    let mut rendered = Vec::with_capacity(run.len());
                                    for &tile in run {
                                        // A frame given up: the scope ends at the next tile.
                                        if give_up.load(Ordering::Relaxed) {
                                            return;
                                        }
                                        let start = Instant::now();
                                        let result = render(tile);
                                        rendered.push((start.elapsed().as_nanos() as u64, result));
                                    }
                                    let _ = sender.send((first, rendered));
                                });
                            }
                        }
                        Message::Done { job: j } if j == job && rank == 0 => {
                            // What follows (a stop, the next phase) is the next job's.
                            done = true;
                            break;
                        }
                        Message::Stop { next_job } if rank == 0 => {
                            // The job this worker is on, or stood ready for, ends here.
                            give_up.store(true, Ordering::Relaxed);
                            self.halt(next_job)?;
                            return Ok(None);
                        }
                        Message::Fail { text } => {
                            return Err(ClusterError::Failed { rank, error: text });
                        }
                        other => return Err(unexpected(rank, &other)),
                    }
                }
                while let Some((first, rendered)) =
                    finished.take().or_else(|| local.try_recv().ok())
                {
                    in_flight -= 1;
                    progressed = true;
                    self.last_frame.tiles_here += rendered.len() as u64;
                    let message = Message::Result {
                        job,
                        first: first as u32,
                        tiles: rendered,
                        want: 1,
                    };
                    self.send(0, &message)?;
                    if let Message::Result { tiles, .. } = message {
                        mine.extend(tiles.into_iter().map(|(_, result)| result));
                    }
                }
                if in_flight > 0 {
                    if let Some(since) = idle_since.take() {
                        self.last_frame.waited += since.elapsed();
                    }
                } else {
                    if done {
                        if let Some(since) = idle_since.take() {
                            self.last_frame.waited += since.elapsed();
                        }
                        return Ok(Some(()));
                    }
                    idle_since.get_or_insert_with(Instant::now);
                }
                if progressed {
                    continue;
                }
                if in_flight > 0 {
                    // Asleep until a run is done: rank 0's answers can wait for it, as
                    // the worker asked for runs in reserve.
                    finished = local.recv_timeout(WORKER_WAKE).ok();
                } else {
                    self.check_silence(0, last_heard.elapsed(), 0)?;
                    std::thread::sleep(POLL);
                }
            }
        })
        .map(|served| served.map(|()| mine))
    }

    /// Gives up on `rank` once it has been silent longer than the time limit.
    pub(super) fn check_silence(
        &self,
        rank: usize,
        waited: Duration,
        outstanding: usize,
    ) -> Result<(), ClusterError> {
        if waited > self.timeout {
            Err(ClusterError::Silent {
                rank,
                waited,
                outstanding,
            })
        } else {
            Ok(())
        }
    }

    pub(super) fn send(&mut self, to: usize, message: &Message) -> Result<(), ClusterError> {
        self.reclaim()?;
        send_counted(&*self.transport, &mut self.last_frame, to, message)
    }

    pub(super) fn receive(&mut self) -> Result<Option<(usize, Message)>, ClusterError> {
        self.reclaim()?;
        receive_counted(&*self.transport, &mut self.last_frame)
    }
}
