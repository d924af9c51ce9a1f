//! Procedural plant species in the spirit of Weber–Penn parametric trees and Xfrog:
//! stems and branches are generalised cylinders grown recursively level by level, leaves
//! are alpha-masked quads along the last level, and each species draws its own leaf
//! texture. A model is deterministic from its [`PlantParams`] and seed, and its triangle
//! count follows the requested budget (from ~500 to ~150 k).

use crate::random::{SceneRng, value_noise};
use glam::{Quat, Vec2, Vec3};
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::shading::{Shader, Texture, linear_to_srgb};

/// Local shader slot of bark and stems in a generated mesh.
pub const BARK: u32 = 0;
/// Local shader slot of the alpha-masked leaves in a generated mesh.
pub const LEAF: u32 = 1;

/// The growth forms of the paper's vegetation layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PlantKind {
    /// Grass and haulm: bent alpha-textured blade cards from one root.
    Grass,
    /// A herb: a few soft stems with leaves, no woody structure.
    Herb,
    /// A low shrub (up to about 1 m): several stems, one branching level.
    LowShrub,
    /// A high shrub (1–4 m): several stems, two branching levels.
    HighShrub,
    /// A low tree (3–8 m): trunk and two branching levels.
    LowTree,
    /// A high tree (8–20 m): trunk and three branching levels.
    HighTree,
    /// A large tree (15–35 m): heavy trunk, three branching levels, wide crown.
    LargeTree,
}

impl PlantKind {
    /// Every kind, smallest first.
    pub const ALL: [PlantKind; 7] = [
        PlantKind::Grass,
        PlantKind::Herb,
        PlantKind::LowShrub,
        PlantKind::HighShrub,
        PlantKind::LowTree,
        PlantKind::HighTree,
        PlantKind::LargeTree,
    ];

    /// The name used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            PlantKind::Grass => "grass",
            PlantKind::Herb => "herb",
            PlantKind::LowShrub => "low_shrub",
            PlantKind::HighShrub => "high_shrub",
            PlantKind::LowTree => "low_tree",
            PlantKind::HighTree => "high_tree",
            PlantKind::LargeTree => "large_tree",
        }
    }

    /// The kind a scene-file name denotes.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// A typical height in metres.
    pub fn typical_height(self) -> f32 {
        match self {
            PlantKind::Grass => 0.5,
            PlantKind::Herb => 0.4,
            PlantKind::LowShrub => 0.8,
            PlantKind::HighShrub => 2.5,
            PlantKind::LowTree => 6.0,
            PlantKind::HighTree => 15.0,
            PlantKind::LargeTree => 25.0,
        }
    }

    /// The leaf shape this kind usually has.
    fn default_leaf(self, rng: &mut SceneRng) -> LeafShape {
        match self {
            PlantKind::Grass => LeafShape::Blades,
            PlantKind::Herb => [LeafShape::Lanceolate, LeafShape::Lobed][rng.below(2) as usize],
            PlantKind::LowShrub | PlantKind::HighShrub => [
                LeafShape::Ellipse,
                LeafShape::Compound,
                LeafShape::Lanceolate,
            ][rng.below(3) as usize],
            _ => [
                LeafShape::Ellipse,
                LeafShape::Lobed,
                LeafShape::Compound,
                LeafShape::Needles,
            ][rng.below(4) as usize],
        }
    }
}

/// The outline a leaf texture's alpha cuts out of its quad.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LeafShape {
    /// Several thin blades side by side (grass cards).
    Blades,
    /// A broad ellipse (beech, lime).
    Ellipse,
    /// A narrow pointed leaf (willow, plantain).
    Lanceolate,
    /// A lobed outline (oak, maple-like).
    Lobed,
    /// Leaflets on both sides of a rachis (ash, rowan).
    Compound,
    /// A spray of needles (conifer twigs).
    Needles,
}

impl LeafShape {
    /// Light a leaf of this shape transmits relative to what it reflects: thin blades and
    /// broad leaves pass on about as much as they reflect (a little less for grass),
    /// thick needles next to nothing.
    pub fn transmission_ratio(self) -> f32 {
        match self {
            LeafShape::Blades => 0.8,
            LeafShape::Needles => 0.0,
            _ => 1.0,
        }
    }

    /// Every shape.
    pub const ALL: [LeafShape; 6] = [
        LeafShape::Blades,
        LeafShape::Ellipse,
        LeafShape::Lanceolate,
        LeafShape::Lobed,
        LeafShape::Compound,
        LeafShape::Needles,
    ];

    /// The name used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            LeafShape::Blades => "blades",
            LeafShape::Ellipse => "ellipse",
            LeafShape::Lanceolate => "lanceolate",
            LeafShape::Lobed => "lobed",
            LeafShape::Compound => "compound",
            LeafShape::Needles => "needles",
        }
    }

    /// The shape a scene-file name denotes.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// Leaf length : width of the quad.
    fn aspect(self) -> f32 {
        match self {
            LeafShape::Blades => 1.0,
            LeafShape::Ellipse => 1.5,
            LeafShape::Lanceolate => 3.0,
            LeafShape::Lobed => 1.3,
            LeafShape::Compound => 1.2,
            LeafShape::Needles => 1.4,
        }
    }
}

/// One branching level: how many children each parent branch carries and how they grow.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BranchLevel {
    /// Children per parent (for level 0: stems from the root).
    pub children: u32,
    /// Where along the parent children start (0 = base, 1 = tip).
    pub start: f32,
    /// Angle between a child and its parent (for level 0: from the vertical), radians.
    pub angle: f32,
    /// Child length relative to its parent (for level 0: relative to the plant height).
    pub length: f32,
    /// Sides of the cylinder.
    pub sides: u32,
    /// Segments along the cylinder.
    pub segments: u32,
}

/// Everything that shapes a species.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantParams {
    /// Growth form.
    pub kind: PlantKind,
    /// Height in metres.
    pub height: f32,
    /// Triangle budget of the model.
    pub triangles: u32,
    /// Branching levels, root first.
    pub levels: Vec<BranchLevel>,
    /// Base radius of level-0 stems relative to the height.
    pub radius: f32,
    /// Downward bend of branches (0 = straight).
    pub gravity: f32,
    /// Leaf (or grass card) length in metres.
    pub leaf_size: f32,
    /// Leaf outline.
    pub leaf_shape: LeafShape,
    /// Linear RGB leaf colour.
    pub leaf_color: Vec3,
    /// Linear RGB bark colour.
    pub bark_color: Vec3,
}

/// A generated species: its mesh (shader slots [`BARK`] and [`LEAF`]), its leaf texture
/// and colours.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantModel {
    /// The mesh, base at the origin, +Y up.
    pub mesh: TriangleMesh,
    /// The alpha-masked leaf texture.
    pub leaf_texture: Texture,
    /// Linear RGB bark colour.
    pub bark_color: Vec3,
    /// Leaf quads (or grass cards) in the mesh.
    pub leaves: u32,
}

fn srgb(r: f32, g: f32, b: f32) -> Vec3 {
    use sylva_engine::shading::srgb_to_linear;
    Vec3::new(srgb_to_linear(r), srgb_to_linear(g), srgb_to_linear(b))
}

impl PlantParams {
    /// Parameters for a species of `kind`, `height` metres tall with about `triangles`
    /// triangles; `seed` varies angles, counts, leaf shape and colours within the kind.
    pub fn for_kind(kind: PlantKind, height: f32, triangles: u32, seed: u64) -> Self {
        let mut rng = SceneRng::new(seed, "species_params");
        let level = |rng: &mut SceneRng,
                     children: u32,
                     start: f32,
                     angle: (f32, f32),
                     length: (f32, f32),
                     sides: u32,
                     segments: u32| BranchLevel {
            children,
            start,
            angle: rng.range(angle.0, angle.1),
            length: rng.range(length.0, length.1),
            sides,
            segments,
        };
        let (herb_stems, low_stems, high_stems) =
            (3 + rng.below(4), 4 + rng.below(4), 4 + rng.below(5));
        let (levels, radius, gravity, leaf_size) = match kind {
            PlantKind::Grass => (vec![], 0.0, 0.0, height),
            PlantKind::Herb => (
                vec![level(
                    &mut rng,
                    herb_stems,
                    0.0,
                    (0.1, 0.5),
                    (0.6, 1.0),
                    3,
                    3,
                )],
                0.012,
                0.1,
                height * rng.range(0.2, 0.35),
            ),
            PlantKind::LowShrub => (
                vec![
                    level(&mut rng, low_stems, 0.0, (0.2, 0.6), (0.6, 1.0), 3, 3),
                    level(&mut rng, 4, 0.25, (0.6, 1.0), (0.3, 0.5), 3, 2),
                ],
                0.02,
                0.2,
                rng.range(0.05, 0.1),
            ),
            PlantKind::HighShrub => (
                vec![
                    level(&mut rng, high_stems, 0.0, (0.2, 0.5), (0.7, 1.0), 4, 4),
                    level(&mut rng, 5, 0.3, (0.6, 1.0), (0.35, 0.55), 3, 3),
                    level(&mut rng, 4, 0.2, (0.5, 0.9), (0.3, 0.5), 3, 1),
                ],
                0.015,
                0.25,
                rng.range(0.07, 0.13),
            ),
            PlantKind::LowTree => (
                vec![
                    level(&mut rng, 1, 0.0, (0.0, 0.08), (0.85, 1.0), 6, 6),
                    level(&mut rng, 8, 0.35, (0.7, 1.1), (0.4, 0.55), 5, 4),
                    level(&mut rng, 6, 0.2, (0.5, 0.9), (0.35, 0.5), 3, 2),
                ],
                0.025,
                0.3,
                rng.range(0.1, 0.18),
            ),
            PlantKind::HighTree => (
                vec![
                    level(&mut rng, 1, 0.0, (0.0, 0.05), (0.9, 1.0), 8, 8),
                    level(&mut rng, 12, 0.4, (0.8, 1.2), (0.3, 0.45), 6, 5),
                    level(&mut rng, 6, 0.2, (0.5, 0.9), (0.4, 0.55), 4, 3),
                    level(&mut rng, 4, 0.2, (0.5, 0.9), (0.4, 0.6), 3, 1),
                ],
                0.02,
                0.35,
                rng.range(0.12, 0.22),
            ),
            PlantKind::LargeTree => (
                vec![
                    level(&mut rng, 1, 0.0, (0.0, 0.05), (0.8, 0.95), 10, 10),
                    level(&mut rng, 14, 0.3, (0.9, 1.3), (0.4, 0.55), 7, 6),
                    level(&mut rng, 6, 0.15, (0.5, 0.9), (0.4, 0.55), 4, 3),
                    level(&mut rng, 4, 0.2, (0.5, 0.9), (0.4, 0.6), 3, 1),
                ],
                0.025,
                0.4,
                rng.range(0.15, 0.25),
            ),
        };
        let leaf_shape = kind.default_leaf(&mut rng);
        let leaf_color = srgb(
            rng.range(0.22, 0.42),
            rng.range(0.42, 0.6),
            rng.range(0.08, 0.22),
        );
        let bark_color = srgb(
            rng.range(0.3, 0.45),
            rng.range(0.24, 0.33),
            rng.range(0.16, 0.24),
        );
        Self {
            kind,
            height,
            triangles,
            levels,
            radius,
            gravity,
            leaf_size,
            leaf_shape,
            leaf_color,
            bark_color,
        }
    }
}

/// One cylinder of the skeleton.
#[derive(Clone, Debug)]
struct Branch {
    path: Vec<Vec3>,
    radii: Vec<f32>,
    sides: u32,
}

impl Branch {
    fn length(&self) -> f32 {
        self.path.windows(2).map(|w| (w[1] - w[0]).length()).sum()
    }

    /// Position and direction at fraction `t` of the path.
    fn at(&self, t: f32) -> (Vec3, Vec3, f32) {
        let segments = self.path.len() - 1;
        let x = (t.clamp(0.0, 1.0) * segments as f32).min(segments as f32 - 1e-4);
        let i = x as usize;
        let f = x - i as f32;
        let p = self.path[i].lerp(self.path[i + 1], f);
        let d = (self.path[i + 1] - self.path[i]).normalize_or(Vec3::Y);
        let r = self.radii[i] + (self.radii[i + 1] - self.radii[i]) * f;
        (p, d, r)
    }

    fn triangles(&self) -> u32 {
        2 * self.sides * (self.path.len() as u32 - 1)
    }
}

/// Grows the skeleton. `scale` multiplies the child counts of the last two levels.
fn skeleton(params: &PlantParams, seed: u64, scale: f32) -> Vec<Vec<Branch>> {
    let mut rng = SceneRng::new(seed, "skeleton");
    let mut levels: Vec<Vec<Branch>> = Vec::new();
    let depth = params.levels.len();
    let count = |i: usize, spec: &BranchLevel| {
        if depth >= 2 && i + 2 >= depth || depth == 1 {
            ((spec.children as f32 * scale).round() as u32).max(1)
        } else {
            spec.children
        }
    };
    for (i, spec) in params.levels.iter().enumerate() {
        let n = count(i, spec);
        let segments = spec.segments.max(1);
        let mut grown = Vec::new();
        let parents: Vec<Option<&Branch>> = if i == 0 {
            vec![None]
        } else {
            levels[i - 1].iter().map(Some).collect()
        };
        for parent in parents {
            for c in 0..n {
                let azimuth = c as f32 * 2.399_963 + rng.range(-0.4, 0.4);
                let (origin, direction, length, radius) = match parent {
                    None => {
                        let tilt = spec.angle * rng.range(0.5, 1.0);
                        let d = Quat::from_rotation_y(azimuth)
                            * (Quat::from_rotation_z(tilt) * Vec3::Y);
                        let spread = if n > 1 { params.height * 0.03 } else { 0.0 };
                        let o = Vec3::new(azimuth.cos(), 0.0, azimuth.sin()) * spread;
                        let len = params.height * spec.length * rng.range(0.85, 1.0);
                        (o, d, len, params.height * params.radius)
                    }
                    Some(parent) => {
                        let t = spec.start
                            + (1.0 - spec.start) * (c as f32 + rng.range(0.2, 0.8)) / n as f32;
                        let (p, d, r) = parent.at(t);
                        let axis = d.any_orthonormal_vector();
                        let side = Quat::from_axis_angle(d, azimuth) * axis;
                        let child = Quat::from_axis_angle(side, spec.angle) * d;
                        // Crowns taper: branches high on the parent are shorter.
                        let len = parent.length() * spec.length * (1.1 - 0.6 * t);
                        (p, child, len, r * 0.7)
                    }
                };
                let step = length / segments as f32;
                let mut path = vec![origin];
                let mut d = direction;
                for _ in 0..segments {
                    let wobble = Vec3::new(rng.range(-0.1, 0.1), 0.0, rng.range(-0.1, 0.1));
                    d = (d - Vec3::Y * params.gravity * 0.3 + wobble).normalize_or(d);
                    path.push(*path.last().expect("path starts non-empty") + d * step);
                }
                let radii = (0..=segments)
                    .map(|k| radius * (1.0 - 0.75 * k as f32 / segments as f32))
                    .collect();
                grown.push(Branch {
                    path,
                    radii,
                    sides: spec.sides.max(3),
                });
            }
        }
        levels.push(grown);
    }
    levels
}

/// Appends meshes piece by piece.
#[derive(Default)]
struct MeshBuilder {
    mesh: TriangleMesh,
}

impl MeshBuilder {
    fn vertex(&mut self, p: Vec3, n: Vec3, uv: Vec2) -> u32 {
        self.mesh.positions.push(p);
        self.mesh.normals.push(n.normalize_or(Vec3::Y));
        self.mesh.uvs.push(uv);
        self.mesh.positions.len() as u32 - 1
    }

    fn triangle(&mut self, a: u32, b: u32, c: u32, shader: u32) {
        self.mesh.indices.push([a, b, c]);
        self.mesh.shaders.push(shader);
    }

    /// A generalised cylinder, frames carried by parallel transport so it does not twist.
    fn tube(&mut self, branch: &Branch) {
        let (path, sides) = (&branch.path, branch.sides);
        let mut prev_dir = (path[1] - path[0]).normalize_or(Vec3::Y);
        let mut normal = prev_dir.any_orthonormal_vector();
        let base = self.mesh.positions.len() as u32;
        for (i, &p) in path.iter().enumerate() {
            let dir = match path.get(i + 1) {
                Some(&next) => (next - p).normalize_or(prev_dir),
                None => prev_dir,
            };
            normal = (Quat::from_rotation_arc(prev_dir, dir) * normal).normalize();
            prev_dir = dir;
            let binormal = dir.cross(normal);
            for s in 0..=sides {
                let a = std::f32::consts::TAU * s as f32 / sides as f32;
                let n = normal * a.cos() + binormal * a.sin();
                self.vertex(
                    p + n * branch.radii[i],
                    n,
                    Vec2::new(s as f32 / sides as f32, i as f32),
                );
            }
        }
        let ring = sides + 1;
        for i in 0..path.len() as u32 - 1 {
            for s in 0..sides {
                let a = base + i * ring + s;
                let (b, c, d) = (a + 1, a + ring, a + ring + 1);
                self.triangle(a, c, b, BARK);
                self.triangle(b, c, d, BARK);
            }
        }
    }

    /// A leaf quad from `base` along `dir`, its face turned towards `facing`; UV (0, 0)
    /// at the tip's left corner so the texture's top row is the tip.
    fn leaf(&mut self, base: Vec3, dir: Vec3, facing: Vec3, length: f32, width: f32) {
        let dir = dir.normalize_or(Vec3::Y);
        let side = dir.cross(facing).normalize_or(dir.any_orthonormal_vector());
        let normal = side.cross(dir);
        let half = side * width * 0.5;
        let tip = base + dir * length;
        let ids = [
            self.vertex(tip - half, normal, Vec2::new(0.0, 0.0)),
            self.vertex(tip + half, normal, Vec2::new(1.0, 0.0)),
            self.vertex(base + half, normal, Vec2::new(1.0, 1.0)),
            self.vertex(base - half, normal, Vec2::new(0.0, 1.0)),
        ];
        self.triangle(ids[0], ids[3], ids[2], LEAF);
        self.triangle(ids[0], ids[2], ids[1], LEAF);
    }

    /// A grass card: a vertical textured strip of `segments` rows bending along `lean`.
    fn card(&mut self, root: Vec3, lean: Vec3, side: Vec3, height: f32, width: f32, segments: u32) {
        let mut rows = Vec::new();
        for s in 0..=segments {
            let t = s as f32 / segments as f32;
            let p = root + Vec3::Y * height * t + lean * height * t * t;
            let tangent = (Vec3::Y + lean * 2.0 * t).normalize();
            let n = side.cross(tangent);
            let half = side * width * 0.5;
            rows.push((
                self.vertex(p - half, n, Vec2::new(0.0, 1.0 - t)),
                self.vertex(p + half, n, Vec2::new(1.0, 1.0 - t)),
            ));
        }
        for s in 0..segments as usize {
            let ((a0, a1), (b0, b1)) = (rows[s], rows[s + 1]);
            self.triangle(a0, b0, a1, LEAF);
            self.triangle(a1, b0, b1, LEAF);
        }
    }
}

/// Leaf quad area per square metre of plant height squared that a budget must afford.
const LEAF_COVERAGE: f32 = 3.0;

/// Rows of a grass card.
const CARD_SEGMENTS: u32 = 3;

/// Generates the species: skeleton sized to the triangle budget, bark cylinders, leaves
/// spread evenly over the last level, and the leaf texture.
pub fn generate(params: &PlantParams, seed: u64) -> PlantModel {
    let mut b = MeshBuilder::default();
    let mut rng = SceneRng::new(seed, "leaves");
    let budget = params.triangles.max(2);
    let leaves;
    if params.levels.is_empty() {
        leaves = (budget / (2 * CARD_SEGMENTS)).max(1);
        for _ in 0..leaves {
            let angle = rng.range(0.0, std::f32::consts::TAU);
            let out = Vec3::new(angle.cos(), 0.0, angle.sin());
            let root = out * rng.range(0.0, params.height * 0.15);
            let lean = out * rng.range(0.05, 0.45);
            let side = Quat::from_rotation_y(rng.range(-0.5, 0.5)) * out.cross(Vec3::Y);
            let h = params.height * rng.range(0.6, 1.1);
            b.card(root, lean, side, h, h * rng.range(0.35, 0.5), CARD_SEGMENTS);
        }
    } else {
        let target_per_twig = match params.kind {
            PlantKind::Herb => 6.0,
            PlantKind::LowShrub | PlantKind::HighShrub => 8.0,
            _ => 14.0,
        };
        // Fit the twig count to the budget: leaves ≈ (budget − structure) / 2 spread at
        // about `target_per_twig` per twig; a few fixed-point steps settle it.
        // Small budgets get coarser cylinders: sides and segments shrink with the
        // budget below 20 k triangles.
        let detail = (budget as f32 / 20_000.0).powf(0.35).min(1.0);
        let mut coarse = params.clone();
        for level in &mut coarse.levels {
            level.sides = ((level.sides as f32 * detail).round() as u32).max(3);
            level.segments = ((level.segments as f32 * detail).round() as u32).max(1);
        }
        let params = &coarse;
        let mut scale = 1.0f32;
        let mut levels = skeleton(params, seed, scale);
        for _ in 0..8 {
            let structure: u32 = levels.iter().flatten().map(Branch::triangles).sum();
            let twigs = levels.last().map_or(1, Vec::len) as f32;
            let leaf_budget = budget.saturating_sub(structure) as f32 / 2.0;
            let ratio = leaf_budget / (twigs * target_per_twig);
            if (0.8..1.25).contains(&ratio) || (scale <= 0.05 && ratio < 1.0) {
                break;
            }
            scale = (scale * ratio.clamp(0.25, 4.0).sqrt()).clamp(0.05, 40.0);
            levels = skeleton(params, seed, scale);
        }
        let structure: u32 = levels.iter().flatten().map(Branch::triangles).sum();
        for branch in levels.iter().flatten() {
            b.tube(branch);
        }
        let twigs = levels.last().expect("a plant has levels");
        leaves = (budget.saturating_sub(structure) / 2).max(twigs.len() as u32);
        // A small budget cannot afford many small leaves: grow them (towards leaf
        // clusters) so the crown keeps about LEAF_COVERAGE × height² of leaf quads.
        let aspect = params.leaf_shape.aspect();
        let needed =
            (LEAF_COVERAGE * params.height * params.height * aspect / leaves as f32).sqrt();
        let leaf_size = params.leaf_size.max(needed.min(params.height * 0.15));
        let width = leaf_size / aspect;
        for k in 0..leaves {
            let twig = &twigs[k as usize % twigs.len()];
            let (p, d, r) = twig.at(rng.range(0.15, 1.0));
            let around = Quat::from_axis_angle(d, rng.range(0.0, std::f32::consts::TAU))
                * d.any_orthonormal_vector();
            let dir = (d * 0.6 + around + Vec3::Y * 0.2).normalize_or(d);
            let facing = (Vec3::Y + rng.unit() * 0.5).normalize_or(Vec3::Y);
            let size = leaf_size * rng.range(0.8, 1.2);
            b.leaf(p + around * r, dir, facing, size, size / leaf_size * width);
        }
    }
    PlantModel {
        mesh: b.mesh,
        leaf_texture: leaf_texture(params.leaf_shape, params.leaf_color, seed),
        bark_color: params.bark_color,
        leaves,
    }
}

/// Edge of a leaf texture in texels.
pub const LEAF_TEXTURE_SIZE: u32 = 64;

/// Draws a leaf texture: the outline as alpha, a darker midrib and veins, colour
/// varying with low-frequency noise and yellowing towards the margin.
pub fn leaf_texture(shape: LeafShape, color: Vec3, seed: u64) -> Texture {
    let n = LEAF_TEXTURE_SIZE;
    let mut rng = SceneRng::new(seed, "leaf_texture");
    let blades: Vec<(f32, f32, f32)> = (0..7)
        .map(|_| {
            (
                rng.range(0.1, 0.9),
                rng.range(-0.15, 0.15),
                rng.range(0.6, 1.0),
            )
        })
        .collect();
    let needles: Vec<(f32, f32)> = (0..22)
        .map(|i| (i as f32 / 21.0 * 1.6 - 0.8, rng.range(0.55, 0.95)))
        .collect();
    let lobes = 3.0 + rng.below(3) as f32;
    let texels = (0..n * n)
        .map(|i| {
            // u across (0 left, 1 right), s along the leaf (0 base, 1 tip).
            let u = ((i % n) as f32 + 0.5) / n as f32;
            let s = 1.0 - ((i / n) as f32 + 0.5) / n as f32;
            let x = u - 0.5;
            let (inside, edge, vein) = match shape {
                LeafShape::Blades => {
                    let hit = blades.iter().any(|&(root, bend, len)| {
                        let centre = root + bend * s * s;
                        let half = 0.045 * (1.0 - s / len).max(0.0);
                        (u - centre).abs() < half && s < len
                    });
                    (hit, 0.0, false)
                }
                LeafShape::Needles => {
                    let hit = x.abs() < 0.02 && s < 0.95
                        || needles.iter().any(|&(slope, len)| {
                            let along = s - 0.05;
                            along > 0.0 && along < len && (x - slope * along * 0.5).abs() < 0.018
                        });
                    (hit, 0.0, x.abs() < 0.02)
                }
                LeafShape::Compound => {
                    let rachis = x.abs() < 0.025 && s < 0.97;
                    let pairs = 4.0;
                    let k = (s * pairs).floor();
                    let local = s * pairs - k - 0.5;
                    let leaflet =
                        s > 0.1 && ((x.abs() - 0.22) / 0.2).powi(2) + (local / 0.38).powi(2) < 1.0;
                    let top = (x / 0.14).powi(2) + ((s - 0.88) / 0.11).powi(2) < 1.0;
                    (rachis || leaflet || top, 0.0, rachis)
                }
                _ => {
                    let s_blade = (s - 0.08) / 0.92;
                    let half = match shape {
                        LeafShape::Ellipse => {
                            0.46 * (std::f32::consts::PI * s_blade).sin().powf(0.8)
                        }
                        LeafShape::Lanceolate => {
                            0.46 * 2.6 * s_blade.max(0.0).sqrt() * (1.0 - s_blade).max(0.0)
                        }
                        _ => {
                            0.4 * (std::f32::consts::PI * s_blade).sin().powf(0.7)
                                * (0.75 + 0.25 * (lobes * std::f32::consts::TAU * s_blade).cos())
                        }
                    };
                    let petiole = s < 0.1 && x.abs() < 0.02;
                    let blade = (0.0..1.0).contains(&s_blade) && x.abs() < half;
                    let edge = if half > 0.0 { x.abs() / half } else { 1.0 };
                    let lateral = ((s_blade * 9.0 + x.abs() * 6.0).fract() - 0.5).abs() < 0.06;
                    (petiole || blade, edge, x.abs() < 0.015 || lateral && blade)
                }
            };
            if !inside {
                return [0, 0, 0, 0];
            }
            let variation = 1.0 + 0.18 * value_noise(seed, u * 6.0, s * 6.0);
            let mut c = color * variation;
            c = c.lerp(
                Vec3::new(c.y * 0.9, c.y, c.z * 0.6),
                0.3 * edge.clamp(0.0, 1.0),
            );
            if vein {
                c *= 0.75;
            }
            let to8 = |v: f32| (linear_to_srgb(v.clamp(0.0, 1.0)) * 255.0 + 0.5) as u8;
            [to8(c.x), to8(c.y), to8(c.z), 255]
        })
        .collect();
    Texture::from_srgba8(n, n, texels).expect("the leaf texture has n×n texels")
}

/// A species model ready for the library: a mesh whose triangles name shaders by local
/// index into `shaders`.
#[derive(Clone, Debug)]
pub struct SpeciesModel {
    /// The mesh.
    pub mesh: TriangleMesh,
    /// Its shaders; their ids are ignored and replaced by the scene's.
    pub shaders: Vec<Shader>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_meets_its_triangle_budget_from_500_to_150k() {
        for kind in PlantKind::ALL {
            for budget in [500u32, 5_000, 50_000, 150_000] {
                let params = PlantParams::for_kind(kind, kind.typical_height(), budget, 11);
                let model = generate(&params, 11);
                let n = model.mesh.triangle_count() as f32;
                let error = (n - budget as f32).abs() / budget as f32;
                assert!(
                    error < 0.2,
                    "{kind:?} at {budget}: {n} triangles ({:.0} %)",
                    error * 100.0
                );
                model.mesh.check().unwrap();
                assert!(model.mesh.positions.iter().all(|p| p.is_finite()));
                assert!(model.leaves > 0);
            }
        }
    }

    #[test]
    fn models_are_deterministic_grounded_and_about_as_tall_as_asked() {
        for kind in PlantKind::ALL {
            let h = kind.typical_height();
            let params = PlantParams::for_kind(kind, h, 4000, 5);
            let a = generate(&params, 5);
            assert_eq!(a, generate(&params, 5), "{kind:?}");
            assert_ne!(a.mesh, generate(&params, 6).mesh, "{kind:?}");
            let bounds = a.mesh.bounds();
            assert!(bounds.min.y > -0.2 * h, "{kind:?} {bounds:?}");
            assert!(
                bounds.max.y > 0.5 * h && bounds.max.y < 1.6 * h,
                "{kind:?}: {bounds:?} for height {h}"
            );
            let leaf = a.mesh.shaders.iter().filter(|&&s| s == LEAF).count();
            assert!(
                leaf > a.mesh.triangle_count() / 3,
                "{kind:?}: mostly leaves"
            );
        }
    }

    #[test]
    fn leaf_textures_cut_a_shape_and_are_opaque_on_the_midrib() {
        for shape in LeafShape::ALL {
            let t = leaf_texture(shape, Vec3::new(0.1, 0.3, 0.05), 3);
            let opaque = (0..LEAF_TEXTURE_SIZE * LEAF_TEXTURE_SIZE)
                .filter(|i| {
                    let uv = Vec2::new(
                        ((i % LEAF_TEXTURE_SIZE) as f32 + 0.5) / LEAF_TEXTURE_SIZE as f32,
                        ((i / LEAF_TEXTURE_SIZE) as f32 + 0.5) / LEAF_TEXTURE_SIZE as f32,
                    );
                    t.sample(uv).w > 0.5
                })
                .count() as f32
                / (LEAF_TEXTURE_SIZE * LEAF_TEXTURE_SIZE) as f32;
            assert!(
                (0.08..0.85).contains(&opaque),
                "{shape:?}: {:.0} % opaque",
                opaque * 100.0
            );
            let mean = t.mean_opaque_color();
            assert!(
                mean.y > mean.x && mean.y > mean.z,
                "{shape:?} is green: {mean}"
            );
        }
        assert_eq!(LeafShape::from_name("lobed"), Some(LeafShape::Lobed));
        assert_eq!(PlantKind::from_name("high_tree"), Some(PlantKind::HighTree));
    }
}
