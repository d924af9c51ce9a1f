//! The editor's operations on a world: selections, inserts that keep their layer's
//! spacing, moves, deletes, undo and redo, wind, and saved ecosystems read back.

use super::*;
use glam::Vec3;

#[test]
fn editor_actions_read_back_from_their_bytes_and_bad_bytes_are_refused() {
    let plant = Entity::from_raw_u32(41).expect("a valid index");
    let actions = [
        EditorAction::Select(3, u32::MAX),
        EditorAction::Insert(0, 7),
        EditorAction::Move(640, 480),
        EditorAction::Delete,
        EditorAction::Undo,
        EditorAction::Redo,
        EditorAction::Wind(true),
        EditorAction::Wind(false),
        EditorAction::SelectPlant(plant),
        EditorAction::SelectAtGround(-0.0, 1e-40),
        EditorAction::InsertAtGround(12.5, -3.25),
        EditorAction::MoveToGround(f32::MAX, 0.1),
    ];
    for action in actions {
        let bytes = action.to_bytes();
        let back = EditorAction::from_bytes(&bytes).expect("reads back");
        // Bit for bit: the sign of a zero counts.
        assert_eq!(format!("{back:?}"), format!("{action:?}"));
        assert_eq!(back.to_bytes(), bytes);
        for len in 0..bytes.len() {
            assert!(
                EditorAction::from_bytes(&bytes[..len]).is_err(),
                "{action:?} cut"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(
            EditorAction::from_bytes(&longer).is_err(),
            "{action:?} extended"
        );
    }
    assert!(EditorAction::from_bytes(&[6, 2]).is_err());
    let unknown = EditorAction::from_bytes(&[11]).unwrap_err();
    assert!(unknown.contains("unknown kind 11"), "{unknown}");
}

/// Every plant as (geometry, layer, transform bits), sorted: equal worlds list equal.
fn listing(world: &mut World) -> Vec<(u32, Option<u32>, [u32; 10])> {
    let mut list: Vec<_> = world
        .query::<(&Instance, &Transform, Option<&Layer>)>()
        .iter(world)
        .map(|(i, t, l)| {
            let mut bits = [0u32; 10];
            let values = [
                t.translation.x,
                t.translation.y,
                t.translation.z,
                t.rotation.x,
                t.rotation.y,
                t.rotation.z,
                t.rotation.w,
                t.scale.x,
                t.scale.y,
                t.scale.z,
            ];
            for (b, v) in bits.iter_mut().zip(values) {
                *b = v.to_bits();
            }
            (i.geometry.0, l.map(|l| l.0), bits)
        })
        .collect();
    list.sort();
    list
}

fn meadow() -> (World, Vec<Entity>) {
    let mut world = World::new();
    let plants = (0..4)
        .map(|i| {
            let t = Transform::from_translation(Vec3::new(i as f32 * 3.0, 0.0, 1.0))
                .with_scale(Vec3::splat(1.0 + i as f32 * 0.1));
            world
                .spawn((
                    t,
                    Instance {
                        geometry: GeometryId(i % 2),
                    },
                    Layer(i),
                ))
                .id()
        })
        .collect();
    (world, plants)
}

/// (species name, layer, transform bits) of every plant, sorted.
fn named_listing(world: &mut World) -> Vec<(String, u32, [u32; 10])> {
    let names: Vec<String> = world
        .resource::<GeometryLibrary>()
        .geometries
        .iter()
        .map(|g| g.name.clone())
        .collect();
    let mut list: Vec<_> = listing(world)
        .into_iter()
        .filter_map(|(g, l, bits)| Some((names[g as usize].clone(), l?, bits)))
        .collect();
    list.sort();
    list
}

#[test]
fn a_saved_ecosystem_loads_back_plant_for_plant() {
    let dir = std::env::temp_dir().join(format!("sylva-save-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let source = dir.join("small.toml");
    std::fs::write(
        &source,
        "[terrain]
size = 20.0\ncells = 8\n\n[[layer]]\nname = \"grass\"\ncount = 6\n\n[[layer.species]]\nname = \"g\"\nkind = \"grass\"\nheight = 0.5\ntriangles = 60\n\n[[layer]]\nname = \"shrubs\"\ncount = 3\n\n[[layer.species]]\nname = \"s\"\nkind = \"low_shrub\"\nheight = 1.0\ntriangles = 80\n",
    )
    .unwrap();
    let mut world = World::new();
    let scene = crate::build_scene(source.to_str().unwrap(), 3).unwrap();
    let spawned = crate::spawn(&mut world, scene);
    let mut history = EditHistory::default();
    history.delete(&mut world, spawned.plants[0]);
    history.move_to(&mut world, spawned.plants[7], (2.5, -3.0));
    let shrub = world.get::<Instance>(spawned.plants[7]).unwrap().geometry;
    history.insert(&mut world, shrub, Some(1), (-4.0, 4.0), 0.7, 1.3);
    let edited = named_listing(&mut world);
    assert_eq!(edited.len(), 9);

    let saved = dir.join("saved.toml");
    let count = save_ecosystem(&mut world, &SceneSource::File(source.clone()), 3, &saved).unwrap();
    assert_eq!(count, 9);
    // Loaded with another seed on the command line: the file's own seed wins.
    let mut again = World::new();
    crate::spawn(
        &mut again,
        crate::build_scene(saved.to_str().unwrap(), 99).unwrap(),
    );
    assert_eq!(named_listing(&mut again), edited);

    let unknown = std::fs::read_to_string(&saved)
        .unwrap()
        .replace("species = \"s\"", "species = \"x\"");
    std::fs::write(&saved, unknown).unwrap();
    let error = crate::build_scene(saved.to_str().unwrap(), 3)
        .unwrap_err()
        .to_string();
    assert!(error.contains("'x'"), "{error}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn wind_on_sways_every_plant_and_wind_off_puts_each_back_at_rest_exactly() {
    let (mut world, plants) = meadow();
    sylva_systems::init_render_world(&mut world, 1).unwrap();
    let start = listing(&mut world);
    assert!(set_wind(&mut world, true, 1.0 / 30.0));
    assert!(world.contains_resource::<Wind>());
    for &plant in &plants {
        let sway = world.get::<Sway>(plant).unwrap();
        assert!(
            sway.omega() > 0.5 && sway.omega() < 10.0,
            "{}",
            sway.omega()
        );
    }
    let mut schedule = sylva_systems::frame_schedule();
    for _ in 0..30 {
        schedule.run(&mut world);
    }
    assert_ne!(listing(&mut world), start, "nothing swayed");
    assert!(!set_wind(&mut world, false, 1.0 / 30.0));
    assert!(!world.contains_resource::<Wind>());
    assert_eq!(listing(&mut world), start);
    assert!(world.get::<Sway>(plants[0]).is_none());
}

#[test]
fn every_edit_undoes_to_the_exact_scene_and_redoes_to_the_edited_one() {
    let (mut world, plants) = meadow();
    let start = listing(&mut world);
    let mut history = EditHistory::default();
    let new = history.insert(&mut world, GeometryId(1), Some(2), (5.0, -4.0), 0.3, 1.5);
    assert!(history.move_to(&mut world, plants[1], (-7.0, 2.0)));
    assert!(history.delete(&mut world, plants[2]));
    assert!(history.move_to(&mut world, new, (1.0, 1.0)));
    assert!(!history.delete(&mut world, plants[2]), "already gone");
    let edited = listing(&mut world);
    assert_eq!(edited.len(), start.len());
    assert_ne!(edited, start);
    // The moved plant keeps its size and stands where it was put.
    let moved = world.get::<Transform>(plants[1]).unwrap();
    assert_eq!((moved.translation.x, moved.translation.z), (-7.0, 2.0));
    assert_eq!(moved.scale, Vec3::splat(1.1));

    let mut steps = 0;
    while history.undo(&mut world) {
        steps += 1;
    }
    assert_eq!(steps, 4);
    assert_eq!(listing(&mut world), start, "undo all");
    while history.redo(&mut world) {}
    assert_eq!(listing(&mut world), edited, "redo all");
    // Back two (the last move and the delete): the deleted plant returns as it was.
    history.undo(&mut world);
    history.undo(&mut world);
    let mid = listing(&mut world);
    assert_eq!(mid.len(), start.len() + 1);
    let deleted = start.iter().find(|p| p.1 == Some(2)).unwrap();
    assert!(mid.contains(deleted), "the deleted plant is back as it was");
    // A new edit drops the redo chain.
    history.delete(&mut world, plants[0]);
    assert!(!history.redo(&mut world));
    assert_eq!(history.undoable(), 3);
}

#[test]
fn a_map_click_selects_the_nearest_plant_whose_crown_covers_it() {
    use sylva_engine::bvh::BuildParams;
    use sylva_engine::geometry::Geometry;
    use sylva_engine::mesh::TriangleMesh;
    let (mut world, plants) = meadow();
    // Crowns of radius 2, times each plant's size (1.0, 1.1, 1.2, 1.3): neighbours'
    // crowns overlap.
    let mut library = GeometryLibrary::default();
    for name in ["a", "b"] {
        let mesh = TriangleMesh {
            positions: vec![
                Vec3::new(-2.0, 0.0, -2.0),
                Vec3::new(2.0, 0.0, -2.0),
                Vec3::new(0.0, 2.0, 2.0),
            ],
            normals: vec![],
            uvs: vec![],
            indices: vec![[0, 1, 2]],
            shaders: vec![0],
        };
        library.add(Geometry::new(name, mesh, BuildParams::BALANCED).unwrap());
    }
    world.insert_resource(library);
    // Plants stand at x = 0, 3, 6, 9 (z = 1).
    assert_eq!(select_at_ground(&mut world, (3.0, 1.0)), Some(plants[1]));
    assert_eq!(world.resource::<Selected>().0, Some(plants[1]));
    // Between two crowns, the nearer stem wins.
    assert_eq!(select_at_ground(&mut world, (4.4, 1.0)), Some(plants[1]));
    assert_eq!(select_at_ground(&mut world, (4.6, 1.0)), Some(plants[2]));
    // Outside every crown: nothing, and the selection is cleared.
    assert_eq!(select_at_ground(&mut world, (3.0, 4.0)), None);
    assert_eq!(world.resource::<Selected>().0, None);
}

#[test]
fn inserts_keep_the_layer_spacing_and_other_layers_do_not_count() {
    let (mut world, plants) = meadow();
    // Layers 0..3 each hold one plant, at x = 0, 3, 6, 9 (z = 1); layer 1 keeps 2 m.
    world.insert_resource(LayerSpacing(vec![0.0, 2.0, 0.0, 0.0]));
    select(&mut world, Some(plants[1]));
    assert_eq!(
        insert_at_ground(&mut world, (4.5, 1.0)),
        None,
        "1.5 m from its layer's plant"
    );
    assert_eq!(
        world
            .get_resource::<EditHistory>()
            .map_or(0, EditHistory::undoable),
        0,
        "a refused insert is no edit"
    );
    // 2 m away is allowed, and the new plant then keeps the next one off.
    let first = insert_at_ground(&mut world, (5.0, 1.0)).expect("2 m from its layer's plant");
    assert_eq!(world.get::<Layer>(first), Some(&Layer(1)));
    assert_eq!(
        insert_at_ground(&mut world, (6.5, 1.0)),
        None,
        "1.5 m from the new one"
    );
    // Next to plant 2 (another layer), 0.5 m off, is fine for layer 1 ...
    select(&mut world, Some(first));
    assert!(insert_at_ground(&mut world, (7.0, 1.0)).is_some());
    // ... and layer 0 has no rule.
    select(&mut world, Some(plants[0]));
    assert!(insert_at_ground(&mut world, (0.1, 1.0)).is_some());
}

#[test]
fn a_scene_files_sway_factors_scale_the_springs_of_their_layer_and_species() {
    let dir = std::env::temp_dir().join(format!("sylva-sway-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = |grass_sway: &str, species_sway: &str| {
        let path = dir.join("sway.toml");
        std::fs::write(
            &path,
            format!(
                "[terrain]
size = 20.0\ncells = 8\n\n[[layer]]\nname = \"grass\"\ncount = 6\n{grass_sway}\n\n[[layer.species]]\nname = \"g\"\nkind = \"grass\"\nheight = 0.5\ntriangles = 60\n{species_sway}\n\n[[layer]]\nname = \"shrubs\"\ncount = 3\n\n[[layer.species]]\nname = \"s\"\nkind = \"low_shrub\"\nheight = 1.0\ntriangles = 80\n"
            ),
        )
        .unwrap();
        let mut world = World::new();
        let spawned = crate::spawn(
            &mut world,
            crate::build_scene(path.to_str().unwrap(), 3).unwrap(),
        );
        set_wind(&mut world, true, 0.1);
        spawned
            .plants
            .iter()
            .map(|&p| {
                let s = world.get::<Sway>(p).unwrap();
                let layer = world.get::<Layer>(p).unwrap().0;
                (layer, s.stiffness, s.damping, s.inertia)
            })
            .collect::<Vec<_>>()
    };
    let plain = scene("", "");
    let tuned = scene(
        "sway = { stiffness = 4.0, damping = 2.0 }",
        "sway = { damping = 3.0 }",
    );
    assert_eq!(plain.len(), tuned.len());
    for (p, t) in plain.iter().zip(&tuned) {
        let ratio = |a: f64, b: f64| b / a;
        let (stiffness, damping) = if p.0 == 0 { (4.0, 3.0) } else { (1.0, 1.0) };
        assert!((ratio(p.1, t.1) - stiffness).abs() < 1e-9, "{p:?} {t:?}");
        assert!(
            (ratio(p.2, t.2) - damping).abs() < 1e-9,
            "the species' damping wins"
        );
        assert_eq!(p.3, t.3, "inertia as the height gives it");
    }
    assert!(tuned.iter().any(|t| t.0 == 0) && tuned.iter().any(|t| t.0 == 1));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_wind_turned_on_is_the_scene_files_or_the_default() {
    let (mut world, _) = meadow();
    assert!(set_wind(&mut world, true, 0.1));
    assert_eq!(*world.resource::<Wind>(), Wind::default());
    set_wind(&mut world, false, 0.1);
    let gale = Wind {
        speed: 20.0,
        ..Wind::default()
    };
    world.insert_resource(SceneWind(gale));
    set_wind(&mut world, true, 0.1);
    assert_eq!(*world.resource::<Wind>(), gale);
}
