//! Key-frame animation of a node hierarchy, as glTF defines it: channels drive a node's
//! translation, rotation or scale with STEP, LINEAR or CUBICSPLINE samplers, and every
//! node's world transform is its parent's times its own (glTF 2.0 §3.11, Appendix C).

use glam::{Affine3A, Quat, Vec3, Vec4};

/// How a sampler interpolates between key frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// The value of the key at or before the time.
    Step,
    /// Straight between keys (rotations: spherical, the shorter way).
    Linear,
    /// Cubic Hermite with the file's in- and out-tangents.
    CubicSpline,
}

/// The property a channel drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Property {
    /// Translation (x, y, z).
    Translation,
    /// Rotation as a quaternion (x, y, z, w).
    Rotation,
    /// Scale (x, y, z).
    Scale,
}

/// One animated property of one node.
#[derive(Clone, Debug, PartialEq)]
pub struct Channel {
    /// Index of the node.
    pub node: usize,
    /// What it drives.
    pub property: Property,
    /// Key times in seconds, increasing.
    pub times: Vec<f32>,
    /// Key values (w unused for vectors); for [`Interpolation::CubicSpline`] three per
    /// key: in-tangent, value, out-tangent.
    pub values: Vec<Vec4>,
    /// The sampler's interpolation.
    pub interpolation: Interpolation,
}

impl Channel {
    /// The channel's value at `time` (clamped to its first and last keys).
    pub fn sample(&self, time: f32) -> Vec4 {
        let cubic = self.interpolation == Interpolation::CubicSpline;
        let value = |k: usize| {
            if cubic {
                self.values[3 * k + 1]
            } else {
                self.values[k]
            }
        };
        let last = self.times.len() - 1;
        if self.times.len() == 1 || time.is_nan() || time <= self.times[0] {
            return value(0);
        }
        if time >= self.times[last] {
            return value(last);
        }
        let k = self.times.partition_point(|&t| t <= time) - 1;
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let span = t1 - t0;
        let s = (time - t0) / span;
        let rotation = self.property == Property::Rotation;
        match self.interpolation {
            Interpolation::Step => value(k),
            Interpolation::Linear if rotation => {
                let (a, b) = (Quat::from_vec4(value(k)), Quat::from_vec4(value(k + 1)));
                Vec4::from(a.normalize().slerp(b.normalize(), s))
            }
            Interpolation::Linear => value(k).lerp(value(k + 1), s),
            Interpolation::CubicSpline => {
                let (p0, m0) = (value(k), self.values[3 * k + 2] * span);
                let (p1, m1) = (value(k + 1), self.values[3 * (k + 1)] * span);
                let (s2, s3) = (s * s, s * s * s);
                let p = p0 * (2.0 * s3 - 3.0 * s2 + 1.0)
                    + m0 * (s3 - 2.0 * s2 + s)
                    + p1 * (-2.0 * s3 + 3.0 * s2)
                    + m1 * (s3 - s2);
                if rotation { p.normalize_or_zero() } else { p }
            }
        }
    }
}

/// A node's local translation, rotation and scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NodeTrs {
    /// Translation.
    pub translation: Vec3,
    /// Rotation.
    pub rotation: Quat,
    /// Scale.
    pub scale: Vec3,
}

impl NodeTrs {
    /// As an affine transform (scale, then rotation, then translation).
    pub fn affine(&self) -> Affine3A {
        Affine3A::from_scale_rotation_translation(self.scale, self.rotation, self.translation)
    }
}

/// A node hierarchy with its rest poses and the channels that move it.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeAnimation {
    /// Each node's parent.
    pub parents: Vec<Option<usize>>,
    /// Each node's local pose without animation.
    pub rest: Vec<NodeTrs>,
    /// The channels of every animation, played together.
    pub channels: Vec<Channel>,
}

impl NodeAnimation {
    /// Seconds until the last key of any channel.
    pub fn duration(&self) -> f32 {
        self.channels
            .iter()
            .filter_map(|c| c.times.last().copied())
            .fold(0.0, f32::max)
    }

    /// Every node's world transform at `time`: its animated local pose under its
    /// parents'.
    pub fn world_transforms(&self, time: f32) -> Vec<Affine3A> {
        let mut local = self.rest.clone();
        for channel in &self.channels {
            let Some(pose) = local.get_mut(channel.node) else {
                continue;
            };
            let v = channel.sample(time);
            match channel.property {
                Property::Translation => pose.translation = v.truncate(),
                Property::Rotation => pose.rotation = Quat::from_vec4(v).normalize(),
                Property::Scale => pose.scale = v.truncate(),
            }
        }
        let mut world: Vec<Option<Affine3A>> = vec![None; local.len()];
        for node in 0..local.len() {
            self.resolve(node, &local, &mut world, 0);
        }
        world
            .into_iter()
            .map(|w| w.unwrap_or(Affine3A::IDENTITY))
            .collect()
    }

    fn resolve(
        &self,
        node: usize,
        local: &[NodeTrs],
        world: &mut [Option<Affine3A>],
        depth: usize,
    ) -> Affine3A {
        if let Some(w) = world[node] {
            return w;
        }
        let parent = match self.parents[node] {
            // A cycle cannot come from a valid file; the depth bound keeps a bad one finite.
            Some(p) if p < local.len() && depth < 1024 => self.resolve(p, local, world, depth + 1),
            _ => Affine3A::IDENTITY,
        };
        let w = parent * local[node].affine();
        world[node] = Some(w);
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(property: Property, interpolation: Interpolation, values: Vec<Vec4>) -> Channel {
        Channel {
            node: 0,
            property,
            times: vec![1.0, 3.0],
            values,
            interpolation,
        }
    }

    #[test]
    fn step_and_linear_follow_the_specs_formulas_and_clamp() {
        let a = Vec4::new(1.0, 2.0, 3.0, 0.0);
        let b = Vec4::new(5.0, -2.0, 3.0, 0.0);
        let step = channel(Property::Translation, Interpolation::Step, vec![a, b]);
        assert_eq!(step.sample(0.0), a);
        assert_eq!(step.sample(2.9), a);
        assert_eq!(step.sample(3.0), b);
        let linear = channel(Property::Translation, Interpolation::Linear, vec![a, b]);
        assert_eq!(linear.sample(2.0), (a + b) * 0.5);
        assert_eq!(linear.sample(1.5), a * 0.75 + b * 0.25);
        assert_eq!(linear.sample(7.0), b);
    }

    #[test]
    fn rotations_are_slerped_the_short_way() {
        let a = Quat::IDENTITY;
        let b = Quat::from_rotation_y(1.5);
        // The same rotation as b with the opposite sign must give the same path.
        for end in [b, -b] {
            let c = channel(
                Property::Rotation,
                Interpolation::Linear,
                vec![Vec4::from(a), Vec4::from(end)],
            );
            let mid = Quat::from_vec4(c.sample(2.0));
            let expected = Quat::from_rotation_y(0.75);
            assert!(1.0 - mid.dot(expected).abs() < 1e-6, "{mid}");
        }
    }

    #[test]
    fn cubic_splines_use_the_tangents_scaled_by_the_key_interval() {
        // p(s) = (2s³−3s²+1)p0 + (s³−2s²+s)·Δt·b0 + (−2s³+3s²)p1 + (s³−s²)·Δt·a1.
        let (p0, b0, a1, p1) = (
            Vec4::new(0.0, 1.0, 0.0, 0.0),
            Vec4::new(1.0, 0.0, 0.0, 0.0),
            Vec4::new(0.0, -2.0, 0.0, 0.0),
            Vec4::new(4.0, 1.0, 2.0, 0.0),
        );
        let c = channel(
            Property::Translation,
            Interpolation::CubicSpline,
            vec![Vec4::ZERO, p0, b0, a1, p1, Vec4::ZERO],
        );
        let dt = 2.0;
        for s in [0.0f32, 0.25, 0.5, 0.9, 1.0] {
            let (s2, s3) = (s * s, s * s * s);
            let expected = p0 * (2.0 * s3 - 3.0 * s2 + 1.0)
                + b0 * dt * (s3 - 2.0 * s2 + s)
                + p1 * (-2.0 * s3 + 3.0 * s2)
                + a1 * dt * (s3 - s2);
            let got = c.sample(1.0 + s * dt);
            assert!(
                (got - expected).length() < 1e-5,
                "s = {s}: {got} vs {expected}"
            );
        }
    }

    #[test]
    fn world_transforms_compose_parents_and_animated_locals() {
        let rest = NodeTrs {
            translation: Vec3::ZERO,
            rotation: Quat::IDENTITY,
            scale: Vec3::ONE,
        };
        let animation = NodeAnimation {
            parents: vec![None, Some(0)],
            rest: vec![
                rest,
                NodeTrs {
                    translation: Vec3::X,
                    ..rest
                },
            ],
            channels: vec![Channel {
                node: 0,
                property: Property::Translation,
                times: vec![0.0, 2.0],
                values: vec![Vec4::ZERO, Vec4::new(0.0, 4.0, 0.0, 0.0)],
                interpolation: Interpolation::Linear,
            }],
        };
        assert_eq!(animation.duration(), 2.0);
        let world = animation.world_transforms(1.0);
        assert_eq!(world[0].translation, Vec3::new(0.0, 2.0, 0.0).into());
        assert_eq!(world[1].translation, Vec3::new(1.0, 2.0, 0.0).into());
    }
}
