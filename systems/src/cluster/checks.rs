//! What every rank compares before it renders: hashes of the scene and of the view,
//! and the per-frame checks rank 0 holds the workers' against.

use super::*;

/// A worker's checks against rank 0's for the same job: every rank renders the same
/// frame of the same scene through the same camera, or the run ends naming the rank.
pub(super) fn compare_checks(
    rank: usize,
    ours: &FrameChecks,
    theirs: &FrameChecks,
) -> Result<(), ClusterError> {
    // Causes first: a changed scene or view also restarts the frame sequence.
    for (what, ours, theirs) in [
        (
            "scene (geometry, plants, shaders or lights)",
            ours.scene,
            theirs.scene,
        ),
        ("camera view or sampling settings", ours.view, theirs.view),
        (
            "progressive frame",
            u64::from(ours.frame),
            u64::from(theirs.frame),
        ),
    ] {
        if ours != theirs {
            return Err(ClusterError::Mismatch { rank, what });
        }
    }
    Ok(())
}

/// The hash every rank compares before a frame: the species BLASes (tree and slot
/// order), the top level (tree and instance records), the shaders and the lights.
pub fn scene_hash(
    library: &GeometryLibrary,
    top_level: &TopLevel,
    shaders: &ShaderTable,
    lights: &LightSet,
) -> u64 {
    let mut hash = Fingerprint::new("sylva cluster scene v2");
    for geometry in &library.geometries {
        hash.u64(geometry.bvh.content_hash());
    }
    hash.u64(top_level.content_hash())
        .u64(shaders.content_hash())
        .u64(lights.content_hash());
    hash.finish()
}

/// The hash of what a camera's frame is drawn with besides the scene: its view and
/// the sampling settings (their `Debug` text, which prints floats exactly).
pub fn view_hash(view: &impl std::fmt::Debug, params: &impl std::fmt::Debug) -> u64 {
    Fingerprint::new("sylva cluster view v1")
        .text(&format!("{view:?}"))
        .text(&format!("{params:?}"))
        .finish()
}
