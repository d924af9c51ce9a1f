//! A model of a cluster frame's time, for machines this one cannot try: N nodes of c
//! cores each, joined by a network of given latency and bandwidth, rendering a frame
//! whose costs were measured here (the tiles' render time on one core, the work rank 0
//! does alone between frames, the bytes the tiles take on the wire).
//!
//! One frame: the cores render the tiles from one queue. Rank 0's node renders at its
//! cores' measured speed; a worker node also sends its tiles back a run at a time, and
//! each send waits for rank 0 to look (`message_wait`, spinning on one of the node's
//! cores), which slows the node and caps it at one run per wait. Rank 0 takes the
//! other nodes' tiles through its link, which bounds the frame; the frame ends one run
//! after the queue empties plus a round trip; and rank 0's own work between frames
//! (accumulating, filtering) is not shared. Frames are pipelined: the worker nodes
//! render the next frame through rank 0's wait for the last tiles and its serial part,
//! so only rank 0's cores stand idle then.

/// The per-frame costs measured on one machine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameCosts {
    /// Seconds one core takes to render every tile of a frame.
    pub tile_work: f64,
    /// Tiles per frame.
    pub tiles: usize,
    /// Tiles handed out together.
    pub run_tiles: usize,
    /// Seconds per frame rank 0 works outside the tiles (not shared out).
    pub serial: f64,
    /// Bytes all of a frame's tiles take on the wire.
    pub frame_bytes: f64,
    /// Throughput per core with every core of a node rendering, relative to one core
    /// alone (1 = perfect scaling inside a node).
    pub node_efficiency: f64,
    /// Seconds a worker's send of a run waits for rank 0 to take it.
    pub message_wait: f64,
}

/// The network between the nodes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Network {
    /// One-way latency of a small message, in seconds.
    pub latency: f64,
    /// Bytes per second into rank 0's node.
    pub bandwidth: f64,
}

impl Network {
    /// Gigabit Ethernet: 50 µs, 117 MB/s.
    pub const GIGABIT: Network = Network {
        latency: 50e-6,
        bandwidth: 117e6,
    };
    /// 10-gigabit Ethernet: 20 µs, 1.17 GB/s.
    pub const TEN_GIGABIT: Network = Network {
        latency: 20e-6,
        bandwidth: 1.17e9,
    };
    /// InfiniBand HDR (200 Gb/s): 1.5 µs, 23 GB/s.
    pub const INFINIBAND: Network = Network {
        latency: 1.5e-6,
        bandwidth: 23e9,
    };
}

/// Where a modelled frame's time goes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameEstimate {
    /// Seconds the cores render.
    pub compute: f64,
    /// Seconds rank 0's link takes for the other nodes' tiles.
    pub transfer: f64,
    /// Seconds after the queue empties: the last run and a round trip.
    pub tail: f64,
    /// Seconds rank 0 works alone.
    pub serial: f64,
    /// Seconds of `compute` the worker nodes do during rank 0's tail and serial part,
    /// rendering the next frame ahead of rank 0.
    pub ahead: f64,
}

impl FrameEstimate {
    /// The frame's time: rank 0's cycle (the rendering the workers have not done ahead,
    /// the tail, the serial part), unless the link takes longer (it carries tiles
    /// throughout).
    pub fn seconds(&self) -> f64 {
        (self.serial + self.tail + self.compute - self.ahead).max(self.transfer)
    }

    /// Frames per second.
    pub fn fps(&self) -> f64 {
        1.0 / self.seconds()
    }
}

impl FrameCosts {
    /// The modelled frame on `nodes` nodes of `cores` cores each.
    pub fn estimate(&self, nodes: usize, cores: usize, network: &Network) -> FrameEstimate {
        let (nodes, cores) = (nodes.max(1), cores.max(1));
        let tile = self.tile_seconds();
        let capacity = cores as f64 * self.efficiency(cores);
        let lead_rate = capacity / tile;
        let worker_rate = self.worker_rate(capacity);
        let remote_rate = (nodes - 1) as f64 * worker_rate;
        let rate = lead_rate + remote_rate;
        let remote_share = remote_rate / rate;
        let compute = self.tiles as f64 / rate;
        let tail = self.run_seconds().min(compute)
            + if nodes > 1 {
                2.0 * network.latency
            } else {
                0.0
            };
        FrameEstimate {
            compute,
            transfer: self.frame_bytes * remote_share / network.bandwidth,
            tail,
            serial: self.serial,
            ahead: Self::ahead(compute, remote_share, tail + self.serial),
        }
    }

    /// Seconds of the frame's rendering done ahead: the workers' share of the rate kept
    /// up through rank 0's `idle` seconds, at most the frame.
    fn ahead(compute: f64, workers_share: f64, idle: f64) -> f64 {
        (workers_share * idle).min(compute)
    }

    /// The modelled frame with `ranks` ranks sharing one node of `cores` cores (the runs
    /// this machine can make): the workers' waiting sends take from the same cores.
    pub fn estimate_on_one_node(&self, ranks: usize, cores: usize) -> FrameEstimate {
        let (ranks, cores) = (ranks.max(1), cores.max(1));
        let capacity = cores as f64 * self.efficiency(cores);
        let workers_share = (ranks - 1) as f64 / ranks as f64;
        let per_tile =
            self.tile_seconds() + workers_share * self.message_wait / self.run_tiles as f64;
        let rate = capacity / per_tile;
        let compute = self.tiles as f64 / rate;
        let tail = self.run_seconds().min(compute);
        FrameEstimate {
            compute,
            transfer: 0.0,
            tail,
            serial: self.serial,
            ahead: Self::ahead(compute, workers_share, tail + self.serial),
        }
    }

    /// Seconds one core takes for one tile.
    fn tile_seconds(&self) -> f64 {
        self.tile_work / self.tiles.max(1) as f64
    }

    /// Seconds one core takes for one run of tiles.
    fn run_seconds(&self) -> f64 {
        self.tile_seconds() * self.run_tiles as f64
    }

    /// Tiles per second of a worker node with `capacity` cores' worth of rendering: each
    /// run's send spins on one of them while it waits, and the node sends one run at a
    /// time.
    fn worker_rate(&self, capacity: f64) -> f64 {
        let spin_per_tile = self.message_wait / self.run_tiles as f64;
        let rate = capacity / (self.tile_seconds() + spin_per_tile);
        if self.message_wait > 0.0 {
            rate.min(self.run_tiles as f64 / self.message_wait)
        } else {
            rate
        }
    }

    /// Per-core efficiency with `cores` cores rendering on one node: 1 for one core,
    /// the measured two-core value beyond (a conservative reading: more cores per node
    /// share more memory bandwidth, which this does not charge further).
    fn efficiency(&self, cores: usize) -> f64 {
        if cores <= 1 {
            1.0
        } else {
            self.node_efficiency
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const COSTS: FrameCosts = FrameCosts {
        tile_work: 2.0,
        tiles: 1200,
        run_tiles: 4,
        serial: 0.05,
        frame_bytes: 22e6,
        node_efficiency: 0.9,
        message_wait: 1e-3,
    };

    #[test]
    fn one_core_takes_the_work_and_the_serial_part() {
        let one = COSTS.estimate(1, 1, &Network::GIGABIT);
        assert_eq!(one.transfer, 0.0);
        assert_eq!(one, COSTS.estimate_on_one_node(1, 1));
        assert!((one.seconds() - (2.0 + 0.05 + 2.0 / 1200.0 * 4.0)).abs() < 1e-12);
    }

    #[test]
    fn more_nodes_are_faster_until_the_link_or_the_serial_part_bounds_them() {
        let mut last = f64::INFINITY;
        for nodes in [1, 2, 4, 8, 16] {
            let t = COSTS.estimate(nodes, 2, &Network::INFINIBAND).seconds();
            assert!(t < last, "{nodes} nodes: {t} s");
            last = t;
        }
        // Gigabit: the other nodes' share of 22 MB a frame (most of it) cannot come in
        // faster than the link takes it, whatever the cores.
        let wide = COSTS.estimate(64, 64, &Network::GIGABIT);
        assert!(wide.transfer > wide.compute);
        assert!(wide.transfer > 0.8 * 22e6 / 117e6);
        assert_eq!(wide.seconds(), wide.transfer);
        // Never faster than the serial part.
        assert!(COSTS.estimate(1024, 64, &Network::INFINIBAND).seconds() > COSTS.serial);
    }

    #[test]
    fn workers_render_the_next_frame_through_rank_0s_serial_part() {
        // One node: nobody to render ahead.
        assert_eq!(COSTS.estimate(1, 2, &Network::INFINIBAND).ahead, 0.0);
        // Two equal nodes: the worker keeps rendering through rank 0's idle time, which
        // saves half of it (rank 0's node is the other half of the rate).
        let costs = FrameCosts {
            message_wait: 0.0,
            ..COSTS
        };
        let two = costs.estimate(2, 2, &Network::INFINIBAND);
        let idle = two.serial + two.tail;
        assert!((two.ahead - idle / 2.0).abs() < 1e-12);
        assert!((two.seconds() - (two.compute + idle / 2.0)).abs() < 1e-12);
        // Many nodes: a frame takes little more than rank 0's serial part and tail.
        let wide = costs.estimate(256, 64, &Network::INFINIBAND);
        assert!(wide.seconds() >= wide.serial + wide.tail);
        assert!(
            wide.seconds() < (wide.serial + wide.tail) * 1.05,
            "{wide:?}"
        );
    }

    #[test]
    fn a_worker_node_sends_at_most_one_run_per_wait() {
        // 64 cores could render 64 / (2 s / 1200) tiles a second; the sends allow 4000.
        let two = COSTS.estimate(2, 64, &Network::INFINIBAND);
        let one = COSTS.estimate(1, 64, &Network::INFINIBAND);
        let added = 1200.0 / two.compute - 1200.0 / one.compute;
        assert!((added - 4.0 / 1e-3).abs() < 1e-6, "{added} tiles/s");
    }

    #[test]
    fn ranks_sharing_a_node_lose_what_their_sends_wait() {
        let alone = COSTS.estimate_on_one_node(1, 2);
        let shared = COSTS.estimate_on_one_node(2, 2);
        assert_eq!(
            alone.compute,
            COSTS.estimate(1, 2, &Network::GIGABIT).compute
        );
        let per_tile = 2.0 / 1200.0;
        let expected = shared.compute / alone.compute;
        assert!((expected - (per_tile + 0.5 * 1e-3 / 4.0) / per_tile).abs() < 1e-12);
    }
}
