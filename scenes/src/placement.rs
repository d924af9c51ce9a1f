//! Plant positions for one vegetation layer: Poisson-disk dart throwing on a grid, with
//! optional noise clustering, that always returns exactly the number asked for.

use crate::random::{SceneRng, fbm};
use glam::Vec2;

/// Where and how a layer places its plants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlacementRule {
    /// Plants to place.
    pub count: u32,
    /// Rectangle `[x0, z0, x1, z1]` in metres.
    pub region: [f32; 4],
    /// Minimum distance between two plants of the layer; `None` picks 0.6 × the mean
    /// spacing, comfortably below the packing limit of random dart throwing.
    pub min_spacing: Option<f32>,
    /// 0 = uniform; towards 1, plants gather where a low-frequency noise is high.
    pub clustering: f32,
    /// Size of the clusters in metres.
    pub cluster_size: f32,
}

impl PlacementRule {
    /// The distance the darts start from: `min_spacing`, or 0.6 × the mean spacing of
    /// `count` points over the region.
    pub fn spacing(&self) -> f32 {
        let [x0, z0, x1, z1] = self.region;
        let area = (x1 - x0).max(1e-3) * (z1 - z0).max(1e-3);
        self.min_spacing
            .unwrap_or_else(|| 0.6 * (area / self.count.max(1) as f32).sqrt())
            .max(0.0)
    }
}

/// Throws darts until `rule.count` points are placed. A dart closer than the spacing to
/// a placed point is rejected; after a run of rejections the spacing shrinks by 5 %, so
/// the count is always met (dense layers end up a little closer than asked). Returns the
/// points and the spacing it ended with, which every two of them keep.
pub fn poisson_disk(rule: &PlacementRule, seed: u64) -> (Vec<Vec2>, f32) {
    let [x0, z0, x1, z1] = rule.region;
    let (width, depth) = ((x1 - x0).max(1e-3), (z1 - z0).max(1e-3));
    let n = rule.count as usize;
    let mut spacing = rule.spacing();
    if n == 0 {
        return (Vec::new(), spacing);
    }
    let area = width * depth;
    // Cells no smaller than the initial spacing keep the 3×3 neighbourhood sufficient
    // as the spacing only ever shrinks; cap the grid at about 4 cells per point.
    let cell = spacing.max((area / (4.0 * n as f32)).sqrt()).max(1e-3);
    let (gw, gd) = (
        ((width / cell).ceil() as usize).max(1),
        ((depth / cell).ceil() as usize).max(1),
    );
    let mut grid: Vec<Vec<u32>> = vec![Vec::new(); gw * gd];
    let mut points: Vec<Vec2> = Vec::with_capacity(n);
    let mut rng = SceneRng::new(seed, "poisson_disk");
    let cluster_seed = seed ^ 0xc1a5_7e2d;
    let clustering = rule.clustering.clamp(0.0, 1.0);
    let mut failures = 0u32;
    while points.len() < n {
        let p = Vec2::new(x0 + rng.f32() * width, z0 + rng.f32() * depth);
        if clustering > 0.0 {
            let noise = fbm(
                cluster_seed,
                p.x / rule.cluster_size,
                p.y / rule.cluster_size,
                3,
                0.5,
            );
            let density = (1.0 - clustering) + clustering * ((noise + 0.3) * 2.0).clamp(0.0, 1.0);
            if rng.f32() >= density {
                continue;
            }
        }
        let (cx, cz) = (
            (((p.x - x0) / cell) as usize).min(gw - 1),
            (((p.y - z0) / cell) as usize).min(gd - 1),
        );
        let blocked = spacing > 0.0
            && (cz.saturating_sub(1)..(cz + 2).min(gd)).any(|z| {
                (cx.saturating_sub(1)..(cx + 2).min(gw)).any(|x| {
                    grid[z * gw + x]
                        .iter()
                        .any(|&i| points[i as usize].distance_squared(p) < spacing * spacing)
                })
            });
        if blocked {
            failures += 1;
            if failures > 64 {
                spacing *= 0.95;
                failures = 0;
            }
            continue;
        }
        failures = 0;
        grid[cz * gw + cx].push(points.len() as u32);
        points.push(p);
    }
    (points, spacing)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule(count: u32, min_spacing: Option<f32>, clustering: f32) -> PlacementRule {
        PlacementRule {
            count,
            region: [-20.0, -10.0, 20.0, 10.0],
            min_spacing,
            clustering,
            cluster_size: 8.0,
        }
    }

    fn min_distance(points: &[Vec2]) -> f32 {
        let mut best = f32::INFINITY;
        for (i, a) in points.iter().enumerate() {
            for b in &points[i + 1..] {
                best = best.min(a.distance(*b));
            }
        }
        best
    }

    #[test]
    fn exact_count_inside_the_region_with_the_spacing_kept() {
        let (points, _) = poisson_disk(&rule(300, Some(1.0), 0.0), 1);
        assert_eq!(points.len(), 300);
        assert!(
            points
                .iter()
                .all(|p| (-20.0..20.0).contains(&p.x) && (-10.0..10.0).contains(&p.y))
        );
        assert!(min_distance(&points) >= 1.0);
        assert_eq!(points, poisson_disk(&rule(300, Some(1.0), 0.0), 1).0);
    }

    #[test]
    fn an_impossible_spacing_relaxes_instead_of_looping_forever() {
        // 2000 points at 2 m spacing cannot fit in 800 m²; the count is still met.
        let (points, spacing) = poisson_disk(&rule(2000, Some(2.0), 0.0), 2);
        assert_eq!(points.len(), 2000);
        assert!(spacing < 2.0, "relaxed to {spacing}");
        assert!(
            min_distance(&points) >= spacing,
            "every pair keeps the spacing it ended with"
        );
    }

    #[test]
    fn clustering_makes_density_uneven() {
        let variance = |points: &[Vec2]| {
            // Occupancy variance over 4 m × 4 m bins.
            let mut bins = [0f32; 50];
            for p in points {
                let (bx, bz) = (((p.x + 20.0) / 4.0) as usize, ((p.y + 10.0) / 4.0) as usize);
                bins[bz.min(4) * 10 + bx.min(9)] += 1.0;
            }
            let mean = bins.iter().sum::<f32>() / 50.0;
            bins.iter().map(|b| (b - mean).powi(2)).sum::<f32>() / 50.0
        };
        let uniform = variance(&poisson_disk(&rule(800, None, 0.0), 3).0);
        let clustered = variance(&poisson_disk(&rule(800, None, 0.9), 3).0);
        assert!(clustered > 3.0 * uniform, "{clustered} vs {uniform}");
    }
}
