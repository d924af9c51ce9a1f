//! A camera's sampling quality as one value: the interactive and still presets (defined
//! here once for the CLI, `converge`, the benches and embedding programs), a fingerprint
//! of what a film's pixels depend on, and how a quality is put on a camera entity.

use bevy_ecs::prelude::*;
use sylva_engine::Camera;
use sylva_engine::discontinuity::{DiscontinuityFilter, FilteredImage};
pub use sylva_engine::fingerprint::Fingerprint;
use sylva_engine::interleave::LightInterleave;
use sylva_engine::transparency::TransparencyCurve;

/// How a camera samples its frames, and how its image is shown.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quality {
    /// Camera samples per pixel in one frame.
    pub samples_per_pixel: u32,
    /// Light samples (sky shadow rays) per camera hit.
    pub light_samples: u32,
    /// Diffuse bounces of indirect light after the first hit (0: direct light only).
    pub bounces: u32,
    /// Adaptive transparency (alpha holes far away turned opaque); exact when `None`.
    pub transparency: Option<TransparencyCurve>,
    /// Interleaved light subsets.
    pub interleave: LightInterleave,
    /// The discontinuity filter on the shown image (the film stays unfiltered).
    pub filter: Option<DiscontinuityFilter>,
}

impl Default for Quality {
    /// Between the presets: 4 camera samples and 2 light samples per hit, exact
    /// transparency, interleaved light subsets, unfiltered.
    fn default() -> Self {
        Self {
            samples_per_pixel: 4,
            light_samples: 2,
            bounces: 0,
            transparency: None,
            interleave: LightInterleave::default(),
            filter: None,
        }
    }
}

impl Quality {
    /// The paper's interactive quality: 1 camera sample and 1 light sample per hit,
    /// adaptive transparency with the default curve, interleaved light subsets and the
    /// discontinuity filter that goes with their pattern: fast frames to refine
    /// progressively.
    pub fn interactive() -> Self {
        let interleave = LightInterleave::default();
        Self {
            samples_per_pixel: 1,
            light_samples: 1,
            transparency: Some(TransparencyCurve::default()),
            interleave,
            filter: Some(DiscontinuityFilter::for_pattern(interleave.pattern)),
            ..Self::default()
        }
    }

    /// The still quality: 4 camera samples and 4 light samples per hit, exact
    /// transparency, unfiltered.
    pub fn still() -> Self {
        Self {
            samples_per_pixel: 4,
            light_samples: 4,
            ..Self::default()
        }
    }

    /// A hash of everything in this quality that a film's pixels depend on (the filter
    /// only changes what is shown, so it is left out), stable across runs, platforms and
    /// versions of the types' `Debug` output: checkpoints and caches carry it.
    pub fn fingerprint(&self) -> u64 {
        let mut hash = Fingerprint::new("quality v1");
        hash.u32(self.samples_per_pixel)
            .u32(self.light_samples)
            .u32(self.bounces)
            .u32(self.interleave.pattern)
            .u32(self.interleave.subsets);
        match self.transparency {
            None => hash.u32(0),
            Some(curve) => hash
                .u32(1)
                .f32(curve.near)
                .f32(curve.far)
                .u32(curve.depth_near)
                .u32(curve.depth_far)
                .f32(curve.weight),
        };
        hash.finish()
    }

    /// Puts this quality on `camera`: its `Camera` sample counts and the components the
    /// planning and display stages read. A change restarts the camera's accumulation.
    pub fn apply(&self, world: &mut World, camera: Entity) {
        let mut entity = world.entity_mut(camera);
        if let Some(mut c) = entity.get_mut::<Camera>() {
            c.samples_per_pixel = self.samples_per_pixel;
            c.light_samples = self.light_samples;
            c.bounces = self.bounces;
        }
        entity.insert(self.interleave);
        match self.transparency {
            Some(curve) => entity.insert(curve),
            None => entity.remove::<TransparencyCurve>(),
        };
        entity.remove::<FilteredImage>();
        match self.filter {
            Some(filter) => entity.insert(filter),
            None => entity.remove::<DiscontinuityFilter>(),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fingerprint_sees_every_setting_the_film_depends_on_and_not_the_filter() {
        let base = Quality::interactive();
        let changed = [
            Quality {
                samples_per_pixel: 2,
                ..base
            },
            Quality {
                light_samples: 2,
                ..base
            },
            Quality { bounces: 1, ..base },
            Quality {
                transparency: None,
                ..base
            },
            Quality {
                transparency: Some(TransparencyCurve {
                    weight: 0.5,
                    ..TransparencyCurve::default()
                }),
                ..base
            },
            Quality {
                interleave: LightInterleave {
                    pattern: 2,
                    subsets: 0,
                },
                ..base
            },
            Quality {
                interleave: LightInterleave {
                    pattern: 4,
                    subsets: 7,
                },
                ..base
            },
            Quality::still(),
            Quality::default(),
        ];
        let mut prints: Vec<u64> = changed.iter().map(Quality::fingerprint).collect();
        prints.push(base.fingerprint());
        let count = prints.len();
        prints.sort_unstable();
        prints.dedup();
        assert_eq!(prints.len(), count, "two qualities share a fingerprint");
        let unfiltered = Quality {
            filter: None,
            ..base
        };
        assert_eq!(unfiltered.fingerprint(), base.fingerprint());
    }

    #[test]
    fn the_fingerprint_is_fnv1a_of_the_values_in_a_fixed_layout() {
        // Values computed independently (Python, FNV-1a 64 over the little-endian
        // layout): a change of layout must change the tag, so that old checkpoints are
        // refused rather than misread.
        assert_eq!(Fingerprint::new("x").u32(1).finish(), 0x52e1_1a78_d605_96a5);
        // Tag, then spp 4, light samples 4, bounces 0, pattern 4, subsets 0, no curve.
        assert_eq!(Quality::still().fingerprint(), 0xdeed_0a32_c858_92d9);
        assert_ne!(
            Fingerprint::new("ab").text("c").finish(),
            Fingerprint::new("a").text("bc").finish()
        );
    }

    #[test]
    fn applying_a_quality_sets_the_camera_and_its_components() {
        let mut world = World::new();
        let camera = world.spawn(Camera::default()).id();
        Quality::interactive().apply(&mut world, camera);
        let entity = world.entity(camera);
        assert_eq!(entity.get::<Camera>().unwrap().samples_per_pixel, 1);
        assert!(entity.contains::<TransparencyCurve>());
        assert!(entity.contains::<DiscontinuityFilter>());
        Quality {
            bounces: 2,
            ..Quality::still()
        }
        .apply(&mut world, camera);
        let entity = world.entity(camera);
        let c = entity.get::<Camera>().unwrap();
        assert_eq!((c.samples_per_pixel, c.light_samples, c.bounces), (4, 4, 2));
        assert!(!entity.contains::<TransparencyCurve>());
        assert!(!entity.contains::<DiscontinuityFilter>());
        assert_eq!(
            entity.get::<LightInterleave>(),
            Some(&LightInterleave::default())
        );
    }
}
