//! The AVX2 and portable kernels give the same bits.

use super::*;

fn uniform(state: &mut u64) -> f32 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*state >> 40) as f32 / (1u64 << 24) as f32
}

/// Nodes and rays with the awkward values: unused lanes, boxes the origin sits on,
/// axis-parallel and denormal directions, NaN.
fn cases() -> Vec<(NodeRay, WideNode, f32)> {
    let mut state = 7;
    let specials = [0.0, -0.0, 1e-40, -1e-40, f32::INFINITY, f32::NAN, 1.0, -1.0];
    let mut out = Vec::new();
    for i in 0..4000 {
        let mut node = WideNode::empty();
        for lane in 0..WIDTH {
            if (i + lane) % 5 == 0 {
                continue;
            }
            let mut c = [0.0; 6];
            for v in &mut c {
                *v = (uniform(&mut state) - 0.5) * 8.0;
            }
            if (i + lane) % 3 == 0 {
                // Flat, as a leaf's box can be: entry and exit coincide.
                c[3 + lane % 3] = c[lane % 3];
            }
            let b = crate::util::math::Aabb {
                min: glam::Vec3A::new(c[0].min(c[3]), c[1].min(c[4]), c[2].min(c[5])),
                max: glam::Vec3A::new(c[0].max(c[3]), c[1].max(c[4]), c[2].max(c[5])),
            };
            node.set_box(lane, b);
        }
        let mut origin = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * 10.0);
        let mut direction = [0.0; 3].map(|_: f32| uniform(&mut state) - 0.5);
        if i % 3 == 0 {
            direction[i % 3] = specials[(i / 3) % specials.len()];
        }
        if i % 7 == 0 {
            // On a face of lane 1's box.
            origin[0] = node.min_x[1];
        }
        let ray = crate::util::math::Ray::new(origin.into(), direction.into());
        let t_max = [f32::INFINITY, 3.0, 0.5][i % 3];
        out.push((NodeRay::new(&ray), node, t_max));
    }
    out
}

/// The AVX2 token; these tests need an AVX2 machine (CI has one).
#[cfg(target_arch = "x86_64")]
fn avx2_here() -> Avx2 {
    Avx2::on_this_cpu().expect("this test needs an AVX2 machine (CI has one)")
}

#[test]
fn transforms_from_packed_columns_transform_as_the_scalar_ones() {
    let mut state = 11;
    for case in 0..1000 {
        let mut values = [0.0f32; 13];
        for v in &mut values {
            *v = (uniform(&mut state) - 0.5) * 10f32.powi(case % 7 - 3);
        }
        // The padding value must not leak into any lane the transform uses.
        values[12] = [f32::NAN, f32::INFINITY, 1e-40, -7.0][case as usize % 4];
        let packed = affine_from_columns(&values);
        let scalar = Affine3A::from_cols_slice(&values[..12]);
        assert_eq!(packed.to_cols_array(), scalar.to_cols_array());
        let p = glam::Vec3A::new(uniform(&mut state), -2.0, uniform(&mut state) * 1e3);
        let (a, b) = (packed.transform_point3a(p), scalar.transform_point3a(p));
        assert_eq!(
            a.to_array().map(f32::to_bits),
            b.to_array().map(f32::to_bits)
        );
        let (a, b) = (packed.transform_vector3a(p), scalar.transform_vector3a(p));
        assert_eq!(
            a.to_array().map(f32::to_bits),
            b.to_array().map(f32::to_bits)
        );
    }
}

#[cfg(target_arch = "x86_64")]
#[test]
fn avx2_and_portable_kernels_give_the_same_bits() {
    let avx2 = avx2_here();
    let mut hits = 0;
    for (ray, node, t_max) in cases() {
        let (t_a, s_a, m_a) = avx2.hit_children_spans(&ray, &node, t_max);
        let (t_p, s_p, m_p) = Portable.hit_children_spans(&ray, &node, t_max);
        assert_eq!(m_a, m_p, "masks differ for {ray:?} {node:?}");
        for lane in 0..WIDTH {
            assert_eq!(t_a[lane].to_bits(), t_p[lane].to_bits(), "lane {lane}");
            assert_eq!(
                s_a[lane].to_bits(),
                s_p[lane].to_bits(),
                "span, lane {lane}"
            );
        }
        hits += m_a.count_ones();
    }
    assert!(hits > 1000, "too few boxes hit ({hits}) to compare");
}

#[cfg(target_arch = "x86_64")]
#[test]
fn avx2_and_portable_packet_bounds_give_the_same_bits() {
    let avx2 = avx2_here();
    let (mut bounds, mut hits) = (0, 0);
    for (i, (ray, node, t_max)) in cases().into_iter().enumerate() {
        // A packet from the case's origin, its directions spread around the case's.
        let mut state = i as u64 + 1;
        let spread = [0.001, 0.05, 0.5][i % 3];
        let rays: Vec<NodeRay> = (0..1 + i % PACKET)
            .map(|_| {
                let d = glam::Vec3A::from(ray.inv_dir).recip()
                    + glam::Vec3A::new(
                        uniform(&mut state) - 0.5,
                        uniform(&mut state) - 0.5,
                        uniform(&mut state) - 0.5,
                    ) * spread;
                NodeRay::new(&crate::util::math::Ray::new(ray.origin.into(), d))
            })
            .collect();
        let Some(bound) = PacketBound::new(&rays) else {
            continue;
        };
        bounds += 1;
        // A packet's limit is its farthest ray's: mostly open.
        let limit = if i % 4 == 0 { t_max } else { f32::INFINITY };
        let (t_a, m_a) = avx2.packet_hit_children(&bound, &node, limit);
        let (t_p, m_p) = Portable.packet_hit_children(&bound, &node, limit);
        assert_eq!(m_a, m_p, "masks differ for {bound:?} {node:?}");
        for lane in 0..WIDTH {
            assert_eq!(t_a[lane].to_bits(), t_p[lane].to_bits(), "lane {lane}");
        }
        hits += m_a.count_ones();
    }
    assert!(bounds > 1000, "only {bounds} packets could be bounded");
    assert!(hits > 500, "too few boxes hit ({hits}) to compare");
}

#[cfg(target_arch = "x86_64")]
#[test]
fn avx2_and_portable_leaf_lanes_agree() {
    let avx2 = avx2_here();
    let mut node = WideNode::empty();
    // Every pattern of leaf lanes, with counts up to the largest a lane can hold.
    for pattern in 0..256u32 {
        for lane in 0..WIDTH {
            let leaf = pattern >> lane & 1 == 1;
            node.counts[lane] = if leaf {
                [1, 4, 255, u32::MAX][lane % 4]
            } else {
                0
            };
        }
        assert_eq!(Portable.leaf_lanes(&node), pattern);
        assert_eq!(avx2.leaf_lanes(&node), pattern, "counts {:?}", node.counts);
    }
}

#[cfg(target_arch = "x86_64")]
#[test]
fn avx2_and_portable_instance_boxes_give_the_same_bits() {
    let avx2 = avx2_here();
    let mut state = 5;
    let points: Vec<glam::Vec3> = (0..300)
        .map(|_| glam::Vec3::new(uniform(&mut state) - 0.5, uniform(&mut state) * 4.0, 0.3))
        .collect();
    let table = SupportTable::new(&points);
    for i in 0..5_000 {
        let scale = 10f32.powi(i % 7 - 3);
        let mut entry = || (uniform(&mut state) - 0.5) * scale;
        let mut transform = Affine3A::from_cols_array(&[0.0; 12].map(|_: f32| entry()));
        if i % 5 == 0 {
            // Plant-like: a turn about the stem, axis-aligned rows included.
            transform = Affine3A::from_rotation_y(i as f32 * 0.25);
        }
        let (a, p) = (
            avx2.transformed_bounds(&table, &transform),
            table.transformed_bounds(&transform),
        );
        let bits = |b: Aabb| [b.min.to_array(), b.max.to_array()].map(|v| v.map(f32::to_bits));
        assert_eq!(bits(a), bits(p), "case {i}: {transform:?}");
    }
}

#[cfg(target_arch = "x86_64")]
#[test]
fn avx2_and_portable_block_tests_give_the_same_bits() {
    let avx2 = avx2_here();
    let mut state = 11;
    let specials = [0.0, -0.0, 1e-40, f32::INFINITY, f32::NAN, 1e30, -1e-30];
    let (mut passed, mut compared, mut hits) = (0, 0, 0);
    for i in 0..20_000 {
        let scale = 10f32.powi(i % 5 - 2);
        let mut corner =
            || glam::Vec3A::from([0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * scale));
        let count = 1 + i as usize % 4;
        let mut triangles: Vec<(u32, [glam::Vec3A; 3])> = (0..count)
            .map(|t| (t as u32, [corner(), corner(), corner()]))
            .collect();
        if i % 7 == 0 {
            // Degenerate: an edge function is exactly zero.
            let last = triangles.len() - 1;
            triangles[last].1[2] = triangles[last].1[1];
        }
        if i % 17 == 0 {
            triangles[0].1[1].y = specials[(i / 17) as usize % specials.len()];
        }
        let mut origin = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * 2.0 * scale);
        let on_edge = i % 11 == 0;
        if on_edge {
            // An axis-parallel ray through the edge p0 p1 (made parallel to y): an
            // edge function is exactly zero and the others agree in sign.
            let [p0, p1, _] = &mut triangles[0].1;
            p1.x = p0.x;
            origin[0] = p0.x;
            origin[1] = 0.5 * (p0.y + p1.y);
        }
        let block = TriangleBlock::new(&triangles);
        // Aimed near the first triangle, so lanes pass and fail in about equal shares.
        let [p0, p1, p2] = triangles[0].1;
        let noise = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * scale * 0.6);
        let target = (p0 + p1 + p2) / 3.0 + glam::Vec3A::from(noise);
        let mut direction = (target - glam::Vec3A::from(origin)).to_array();
        if i % 5 == 0 {
            direction[i as usize % 3] = specials[(i / 5) as usize % specials.len()];
        }
        if on_edge {
            direction = [0.0, 0.0, if i % 2 == 0 { 1.0 } else { -1.0 }];
        }
        let ray = crate::util::math::Ray::new(origin.into(), direction.into());
        if !ray.direction.is_finite() || ray.direction == glam::Vec3A::ZERO {
            continue;
        }
        let watertight = WatertightRay::new(&ray);
        passed += watertight.possible_hits(&block, count).count_ones();
        compared += count as u32;
        // Ends that cut some hits off.
        let reach = (target - glam::Vec3A::from(origin)).length();
        let t_max = [f32::INFINITY, reach, 0.5 * reach, 0.0][i as usize % 4];
        let a = avx2.block_hits(&watertight, &block, count, t_max);
        let p = Portable.block_hits(&watertight, &block, count, t_max);
        assert_eq!(
            a.mask, p.mask,
            "block {triangles:?}, {ray:?}, t_max {t_max}"
        );
        for lane in (0..4).filter(|lane| a.mask >> lane & 1 == 1) {
            let bits = |hits: &BlockHits| {
                let hit = hits.hit(lane);
                (
                    hit.t.to_bits(),
                    hit.barycentrics.to_array().map(f32::to_bits),
                )
            };
            assert_eq!(bits(&a), bits(&p), "lane {lane} of {triangles:?}, {ray:?}");
        }
        hits += a.mask.count_ones();
    }
    assert!(
        passed > compared / 20 && passed < compared * 19 / 20,
        "{passed} of {compared} lanes passed: too one-sided to compare"
    );
    assert!(
        hits > compared / 20 && hits < passed,
        "{hits} of {passed} passing lanes hit: too one-sided to compare"
    );
}
