//! The builder's parts against their definitions: split planes, bins and sweeps.

use super::sah::bin_transform;
use super::*;
use crate::util::test_random::uniform;

#[test]
fn split_planes_part_centroids_as_their_bins_do() {
    let mut state = 0x5b1a_9e11u64;
    for case in 0..2_000 {
        // Centroid boxes near and far from the origin, wide and a few ulps thin.
        let offset = [0.0, -3.0, 1.0e5, -2.5e4][case % 4];
        let width = [1.0e-3, 1.0, 300.0, 4.0e-2][(case / 4) % 4];
        let lo = Vec3A::new(
            offset + uniform(&mut state) * width,
            offset - uniform(&mut state) * width,
            offset,
        );
        let hi = lo + Vec3A::new(width, width * uniform(&mut state), width * 1.0e-4);
        let bins = [2, 8, 16, 32][case % 4];
        let (scale, min) = bin_transform(&Aabb::new(lo, hi), bins);
        for axis in (0..3).filter(|&axis| scale[axis] != 0.0) {
            let on_axis = axis_scale(scale, axis);
            for split in 1..bins {
                let plane = split_plane(on_axis, min, bins, axis, split)
                    .unwrap_or_else(|| panic!("case {case}: no plane for bin {split}"));
                let goes_left = |x: f32| {
                    let mut centroid = min;
                    centroid[axis] = x;
                    bin_on_axis(centroid, on_axis, min, bins) < split
                };
                let near = [plane, plane.next_down(), plane.next_up(), 0.0, -0.0];
                let spread = (0..20)
                    .map(|_| lo[axis] + (uniform(&mut state) * 1.2 - 0.1) * (hi[axis] - lo[axis]));
                for x in near.into_iter().chain(spread) {
                    assert_eq!(x < plane, goes_left(x), "case {case}, axis {axis}, x {x}");
                }
            }
        }
    }
}

#[test]
fn a_pair_splits_as_the_bins_would_split_it() {
    let mut state = 0x9a1e_5eedu64;
    let coordinate = |state: &mut u64| match (uniform(state) * 4.0) as u32 {
        // Shared coordinates and coincident centroids take the other branches.
        0 => 0.25,
        _ => uniform(state) * 2.0 - 1.0,
    };
    for case in 0..20_000 {
        let refs: Vec<PrimRef> = (0..2)
            .map(|i| {
                let lo = Vec3A::new(
                    coordinate(&mut state),
                    coordinate(&mut state),
                    coordinate(&mut state),
                );
                let size = Vec3A::new(uniform(&mut state), uniform(&mut state), 0.1);
                PrimRef::new(&Aabb::new(lo, lo + size * (case % 3) as f32), i)
            })
            .collect();
        let extent = Extent::of(&refs);
        for (name, params) in BuildParams::PRESETS {
            let builder = Builder { params };
            let pair = builder.split_pair(&refs, &extent);
            let binned = builder.binned_split(&refs, &extent, &mut Scratch::new());
            assert_eq!(
                format!("{pair:?}"),
                format!("{binned:?}"),
                "case {case}, {name}"
            );
        }
    }
}
