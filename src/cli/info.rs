//! `sylva info`: a scene's species, triangles, instances, memory and build times.

use super::*;
use std::time::Instant;

/// Runs `sylva info`.
pub(crate) fn run(args: SceneArgs) -> Result<()> {
    let _guard = init_tracing(None);
    let command_start = Instant::now();
    let mut world = World::new();
    let (scene, _) = build(&mut world, &args)?;
    let stats = scene.stats();
    let pool = world.resource::<RenderPool>().clone();
    let descs = scene.instance_descs();
    let start = Instant::now();
    let tlas = pool.install(|| {
        TopLevel::build(
            &scene.library,
            &descs,
            sylva::systems::BuildSettings::default().top_level,
        )
    });
    let tlas_time = start.elapsed();
    let start = Instant::now();
    let shaders = sylva::engine::ShaderTable::new(scene.shaders.clone());
    let opacity = pool.install(|| sylva::engine::OpacityMaps::build(&scene.library, &shaders));
    let opacity_time = start.elapsed();
    let total_time = command_start.elapsed();
    println!("scene            {} (seed {})", scene.name, args.seed);
    println!("species          {}", stats.species);
    for s in &scene.species {
        let count = scene
            .plants
            .iter()
            .filter(|p| p.geometry == s.geometry)
            .count();
        let geometry = scene.library.get(s.geometry);
        let tris = geometry.map_or(0, |g| g.mesh.triangle_count());
        println!(
            "  {:<22} {:>9} triangles  {:>9} instances{}",
            s.name,
            group(tris as u64),
            group(count as u64),
            geometry.map_or(String::new(), height_field_note)
        );
    }
    if let Some(t) = scene.terrain.and_then(|t| scene.library.get(t)) {
        println!(
            "terrain          {} triangles{}",
            group(t.mesh.triangle_count() as u64),
            height_field_note(t)
        );
    }
    println!("layers           {}", scene.layers.len());
    for (i, name) in scene.layers.iter().enumerate() {
        let count = scene.plants.iter().filter(|p| p.layer == i as u32).count();
        println!("  {name:<22} {:>9} plants", group(count as u64));
    }
    println!("plants           {}", group(scene.plants.len() as u64));
    println!("unique triangles {}", group(stats.unique_triangles as u64));
    println!(
        "instances        {} (plants{})",
        group(stats.instances as u64),
        if scene.terrain.is_some() {
            " + terrain"
        } else {
            ""
        }
    );
    println!("instanced tris   {}", group(stats.instanced_triangles));
    let blas_hash = scene
        .library
        .geometries
        .iter()
        .fold(0u64, |h, g| h.rotate_left(5) ^ g.bvh.content_hash());
    println!(
        "tree hashes      TLAS {:016x}, BLASes {:016x}",
        tlas.content_hash(),
        blas_hash
    );
    println!(
        "memory           {:.1} MB (geometry + BLAS {:.1} MB, TLAS {:.1} MB, opacity maps {:.1} MB)",
        (scene.library.memory_bytes() + tlas.memory_bytes() + opacity.memory_bytes()) as f64 / 1e6,
        scene.library.memory_bytes() as f64 / 1e6,
        tlas.memory_bytes() as f64 / 1e6,
        opacity.memory_bytes() as f64 / 1e6
    );
    println!(
        "build times      generation {:.2} s, BLAS {:.2} s, TLAS {:.1} ms, opacity maps {:.1} ms ({} maps) ({} threads)",
        scene.generate_time.as_secs_f64(),
        scene.blas_time.as_secs_f64(),
        tlas_time.as_secs_f64() * 1e3,
        opacity_time.as_secs_f64() * 1e3,
        group(opacity.map_count() as u64),
        pool.threads()
    );
    println!(
        "total            {:.2} s to generate and build everything, peak memory {}",
        total_time.as_secs_f64(),
        peak_memory_bytes().map_or("unknown".into(), |b| format!("{:.0} MB", b as f64 / 1e6))
    );
    Ok(())
}

/// For a mesh proven a height field: its steepest slope, which shadow rays leaving it
/// more steeply skip its walk for.
fn height_field_note(geometry: &sylva::engine::geometry::Geometry) -> String {
    geometry.heightfield().map_or(String::new(), |field| {
        format!(
            ", a height field (steepest slope {:.3})",
            field.max_slope_squared.sqrt()
        )
    })
}
