//! The map panel and the window's small parts against their definitions.

use super::map::{MapView, species_colour};
use super::*;

#[test]
fn the_map_panel_maps_ground_to_pixels_and_back_and_finds_the_plant_under_a_click() {
    use sylva::systems::picking::MapPlant;
    let mut world = World::new();
    let (a, b) = (world.spawn_empty().id(), world.spawn_empty().id());
    let plants = [
        MapPlant {
            entity: a,
            position: glam::Vec2::new(-50.0, -50.0),
            radius: 4.0,
            species: 1,
        },
        MapPlant {
            entity: b,
            position: glam::Vec2::new(50.0, 50.0),
            radius: 0.5,
            species: 2,
        },
    ];
    let map = MapView::new(640, 480, &plants);
    assert_eq!(map.side, 216.0);
    let ground = glam::Vec2::new(12.5, -7.0);
    let p = map.to_panel(ground);
    assert!(map.contains(p.x, p.y));
    assert!((map.to_world(p.x, p.y) - ground).length() < 1e-3);
    let at_a = map.to_panel(plants[0].position);
    assert_eq!(map.plant_at(&plants, at_a.x + 1.0, at_a.y), Some(a));
    let at_b = map.to_panel(plants[1].position);
    // A small plant is still hit within three pixels.
    assert_eq!(map.plant_at(&plants, at_b.x + 2.0, at_b.y), Some(b));
    assert_eq!(map.plant_at(&plants, p.x, p.y), None);
    let mut buffer = vec![0u32; 640 * 480];
    map.draw(&mut buffer, 640, &plants, Some(b));
    let outside = buffer[..640 * 200].iter().all(|&p| p == 0);
    assert!(outside, "the panel drew above itself");
    let (ax, ay) = (at_a.x as usize, at_a.y as usize);
    assert_eq!(buffer[ay * 640 + ax], species_colour(1));
    let (bx, by) = (at_b.x as usize, at_b.y as usize);
    assert_eq!(buffer[by * 640 + bx], species_colour(2));
    assert_eq!(buffer[by * 640 + bx + 4], 0x00ff_ffff, "the selection ring");
}

#[test]
fn the_hud_writes_its_lines_on_a_darkened_band_and_leaves_the_rest() {
    let hud = Hud {
        font: ab_glyph::FontRef::try_from_slice(dejavu::sans::regular()).unwrap(),
        triangles: 1_234_567,
    };
    let shown = ShownImage {
        width: 320,
        height: 200,
        frames: 7,
        frame_time: Duration::from_millis(250),
        instances: 42,
        ..ShownImage::default()
    };
    let mut responsiveness = Responsiveness::default();
    let sent = Instant::now();
    responsiveness.sent(1, sent);
    responsiveness.shown(1, sent + Duration::from_millis(120));
    let lines = hud.lines(&shown, 2.5, &responsiveness);
    assert!(lines[0].starts_with("4.0 fps  7 spp"), "{lines:?}");
    assert_eq!(lines[1], "shown 1 images/s  input to image 120 ms");
    assert!(lines[3].contains("42 instances") && lines[3].contains("1,234,567"));
    let grey = 0x0080_8080;
    let mut buffer = vec![grey; 320 * 200];
    hud.draw(&mut buffer, 320, 200, &lines);
    let band_rows = (0..200)
        .filter(|&y| buffer[y * 320..y * 320 + 4].iter().all(|&p| p != grey))
        .count();
    assert!((60..100).contains(&band_rows), "{band_rows} rows darkened");
    let bright = buffer.iter().filter(|&&p| p & 0xff > 0xc0).count();
    assert!(bright > 200, "only {bright} text pixels");
    assert!(
        buffer[150 * 320..].iter().all(|&p| p == grey),
        "below the band"
    );
}
