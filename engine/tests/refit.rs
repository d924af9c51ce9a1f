//! TLAS and BVH refitting: a refitted tree finds exactly the hits a brute force over the
//! moved instances finds, stays structurally valid, reports its degradation, and refuses
//! the changes only a build can handle.

mod common;

use common::*;
use glam::{Affine3A, Quat, Vec3};
use sylva_engine::bvh::{BuildParams, Bvh, RefitError};
use sylva_engine::geometry::{GeometryId, GeometryLibrary};
use sylva_engine::math::{Aabb, Ray};
use sylva_engine::tlas::{InstanceDesc, RefitRefusal, TopLevel};

/// Each instance tilted about its own origin and nudged, as swaying plants move.
fn swayed(rng: &mut TestRng, descs: &[InstanceDesc], angle: f32) -> Vec<InstanceDesc> {
    descs
        .iter()
        .map(|d| InstanceDesc {
            transform: Affine3A::from_translation(Vec3::from(d.transform.translation))
                * Affine3A::from_quat(Quat::from_scaled_axis(rng.unit() * angle))
                * Affine3A::from_translation(-Vec3::from(d.transform.translation))
                * d.transform,
            ..*d
        })
        .collect()
}

fn world_boxes(lib: &GeometryLibrary, descs: &[InstanceDesc]) -> Vec<Aabb> {
    descs
        .iter()
        .map(|d| {
            lib.get(d.geometry)
                .unwrap()
                .transformed_bounds(&d.transform)
        })
        .collect()
}

fn assert_matches_brute_force(
    lib: &GeometryLibrary,
    tlas: &TopLevel,
    descs: &[InstanceDesc],
    rng: &mut TestRng,
    rays: usize,
) {
    let batch: Vec<Ray> = (0..rays).map(|_| random_ray(rng, 25.0)).collect();
    let hits = assert_tlas_matches_brute_force(lib, tlas, descs, &batch, "refitted");
    assert!(
        hits > rays / 20,
        "the rays must hit something: {hits} of {rays}"
    );
}

#[test]
fn refit_of_unmoved_primitives_reproduces_the_built_tree_bit_for_bit() {
    let mut rng = TestRng::new(3);
    let mesh = random_mesh(&mut rng, 2000, 5.0, 0.3);
    let boxes: Vec<Aabb> = (0..mesh.triangle_count())
        .map(|i| mesh.triangle_bounds(i))
        .collect();
    for (name, params) in BuildParams::PRESETS {
        let built = Bvh::build(&boxes, params);
        let mut refitted = built.clone();
        // Padding slots (block-aligned leaves) get an empty box: refit never reads it.
        let slot_boxes: Vec<Aabb> = built
            .prim_indices
            .iter()
            .map(|&i| boxes.get(i as usize).copied().unwrap_or(Aabb::EMPTY))
            .collect();
        refitted.refit(&slot_boxes).unwrap();
        assert_eq!(refitted.bounds(), built.bounds(), "{name}: root box");
        assert_eq!(refitted.wide, built.wide, "{name}: wide nodes");
        assert_eq!(refitted.sah_cost(), built.sah_cost());
    }
}

#[test]
fn refitted_tlas_equals_brute_force_over_the_moved_instances() {
    let mut rng = TestRng::new(11);
    let lib = random_library(&mut rng, 4, 150);
    let descs = random_instances(&mut rng, 400, 4, (-0.5, 0.5));
    for (name, params) in BuildParams::PRESETS {
        let mut tlas = TopLevel::build(&lib, &descs, params);
        assert_eq!(tlas.degradation(), 1.0);
        let mut moved = descs.clone();
        for step in 0..5 {
            moved = swayed(&mut rng, &moved, 0.2);
            let degradation = tlas.refit(&lib, &moved).unwrap();
            assert!(
                degradation.is_finite() && degradation > 0.5,
                "{name}: {degradation}"
            );
            tlas.bvh
                .validate(&world_boxes(&lib, &moved))
                .unwrap_or_else(|e| panic!("{name}, step {step}: {e}"));
            let area: f64 = world_boxes(&lib, &moved)
                .iter()
                .map(|b| b.surface_area() as f64)
                .sum();
            let ratio = tlas.bvh.sah_cost() / area / tlas.built_sah_cost;
            assert!(
                (ratio as f32 - degradation).abs() < 1e-5,
                "{ratio} {degradation}"
            );
            assert_matches_brute_force(&lib, &tlas, &moved, &mut rng, 300);
        }
        // Records follow the move: every slot holds its instance's new transform.
        for record in &tlas.instances {
            assert_eq!(
                record.object_to_world(),
                moved[record.id as usize].transform
            );
        }
    }
}

#[test]
fn degradation_stays_near_one_for_sway_and_grows_when_instances_scatter() {
    let mut rng = TestRng::new(5);
    let lib = random_library(&mut rng, 3, 150);
    let descs = random_instances(&mut rng, 2000, 3, (-0.5, 0.5));
    let mut tlas = TopLevel::build(&lib, &descs, BuildParams::BALANCED);
    let swaying = swayed(&mut rng, &descs, 0.05);
    let mild = tlas.refit(&lib, &swaying).unwrap();
    assert!((0.9..1.1).contains(&mild), "small sway: {mild}");
    // Every instance teleported to another's place: the tree's leaves now span the
    // whole scene.
    let mut scattered = descs.clone();
    for (i, d) in scattered.iter_mut().enumerate() {
        d.transform.translation = descs[(i * 7919) % descs.len()].transform.translation;
    }
    let scattered_cost = tlas.refit(&lib, &scattered).unwrap();
    eprintln!("degradation: sway {mild}, scattered {scattered_cost}");
    let rebuilt = TopLevel::build(&lib, &scattered, BuildParams::BALANCED);
    assert!(
        scattered_cost > 3.0,
        "scattering must show as degradation: {scattered_cost}"
    );
    assert!(tlas.bvh.sah_cost() > 3.0 * rebuilt.bvh.sah_cost());
    assert_matches_brute_force(&lib, &tlas, &scattered, &mut rng, 200);
}

#[test]
fn refit_refuses_what_only_a_build_can_do_and_leaves_the_tree_unchanged() {
    let mut rng = TestRng::new(8);
    let lib = random_library(&mut rng, 2, 150);
    let mut descs = random_instances(&mut rng, 50, 2, (-0.5, 0.5));
    descs[7].transform = Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0));
    let tlas = TopLevel::build(&lib, &descs, BuildParams::BALANCED);
    assert_eq!(tlas.skipped.ids, vec![7]);
    let try_refit = |changed: &[InstanceDesc]| {
        let mut copy = tlas.clone();
        let result = copy.refit(&lib, changed);
        if result.is_err() {
            assert_eq!(copy.bvh.wide, tlas.bvh.wide);
            assert_eq!(copy.instances, tlas.instances);
        }
        result
    };
    assert_eq!(
        try_refit(&descs[..49]),
        Err(RefitRefusal::InstanceCount {
            built: 50,
            given: 49
        })
    );
    let mut other_geometry = descs.clone();
    other_geometry[3].geometry = GeometryId(1 - other_geometry[3].geometry.0);
    assert_eq!(
        try_refit(&other_geometry),
        Err(RefitRefusal::GeometryChanged { instance: 3 })
    );
    let mut singular = descs.clone();
    singular[12].transform.translation.x = f32::NAN;
    assert_eq!(
        try_refit(&singular),
        Err(RefitRefusal::UsableSetChanged { instance: 12 })
    );
    let mut revived = descs.clone();
    revived[7].transform = Affine3A::IDENTITY;
    assert_eq!(
        try_refit(&revived),
        Err(RefitRefusal::UsableSetChanged { instance: 7 })
    );
    // The still-singular instance 7 does not stop a refit of the others.
    assert!(try_refit(&swayed(&mut rng, &descs, 0.1)).is_ok());

    let mut bvh = Bvh::build(&world_boxes(&lib, &descs[..6]), BuildParams::BALANCED);
    assert_eq!(
        bvh.refit(&[Aabb::EMPTY; 3]),
        Err(RefitError::SlotCount {
            expected: 6,
            given: 3
        })
    );
    let mut bad = world_boxes(&lib, &descs[..6]);
    bad[4].max.y = f32::INFINITY;
    assert_eq!(bvh.refit(&bad), Err(RefitError::InvalidBox { slot: 4 }));
}
