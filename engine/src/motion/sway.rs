//! Wind sway of rigid plants: each swaying plant tilts about its base as a damped angular
//! spring, `I θ'' + c θ' + k θ = τ(t)`, per horizontal axis, driven by the torque of a
//! gusty wind field.
//!
//! Integration is exact for a torque held constant over a fixed sub-step `h`: the state
//! relative to the equilibrium `τ/k` is multiplied by the propagator `exp(A h)` of the
//! linear system, computed once per parameter set by scaling and squaring in f64. So it is
//! stable for any stiffness (`k h²/I` of 10⁶ and beyond), conserves energy without damping,
//! loses it monotonically with damping, and a fixed `h` makes the result independent of
//! the frame rate. No explicit step-size limit such as `h < 2/ω` applies.

use bevy_ecs::component::Component;
use bevy_ecs::resource::Resource;
use glam::{DVec2, Quat, Vec2, Vec3};

/// The fixed integration sub-step, seconds (frame times that are multiples of it give
/// identical motion at any frame rate).
pub const SUBSTEP: f64 = 1.0 / 240.0;

/// A plant that sways: spring parameters and its state (tilt about the world X and Z
/// axes through its base). Its entity's `Transform` is `rest` tilted by the state.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct Sway {
    /// Angular stiffness k, N·m/rad (> 0).
    pub stiffness: f64,
    /// Angular damping c, N·m·s/rad (≥ 0).
    pub damping: f64,
    /// Moment of inertia I about the base, kg·m² (> 0).
    pub inertia: f64,
    /// Torque per (m/s)² of wind, N·m·s²/m² (the plant's drag area × lever arm × ½ρ).
    pub wind_gain: f64,
    /// Tilt (about X, about Z), radians.
    pub angle: DVec2,
    /// Tilt rate, rad/s.
    pub velocity: DVec2,
    /// The propagator for `(stiffness, damping, inertia, SUBSTEP)`: row-major 2×2.
    propagator: [f64; 4],
}

/// Why sway parameters were refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error(
    "sway parameters must be finite with stiffness > 0, inertia > 0, damping >= 0 (got k {stiffness}, c {damping}, I {inertia})"
)]
pub struct SwayError {
    /// The stiffness given.
    pub stiffness: f64,
    /// The damping given.
    pub damping: f64,
    /// The inertia given.
    pub inertia: f64,
}

impl Sway {
    /// A plant at rest with these spring parameters.
    pub fn new(
        stiffness: f64,
        damping: f64,
        inertia: f64,
        wind_gain: f64,
    ) -> Result<Self, SwayError> {
        let valid = [stiffness, damping, inertia, wind_gain]
            .iter()
            .all(|v| v.is_finite())
            && stiffness > 0.0
            && inertia > 0.0
            && damping >= 0.0;
        if !valid {
            return Err(SwayError {
                stiffness,
                damping,
                inertia,
            });
        }
        Ok(Self {
            stiffness,
            damping,
            inertia,
            wind_gain,
            angle: DVec2::ZERO,
            velocity: DVec2::ZERO,
            propagator: propagator(stiffness / inertia, damping / inertia, SUBSTEP),
        })
    }

    /// Natural angular frequency ω = √(k/I).
    pub fn omega(&self) -> f64 {
        (self.stiffness / self.inertia).sqrt()
    }

    /// Mechanical energy ½Iθ'² + ½kθ² (both axes).
    pub fn energy(&self) -> f64 {
        0.5 * self.inertia * self.velocity.length_squared()
            + 0.5 * self.stiffness * self.angle.length_squared()
    }

    /// Advances one sub-step under `torque` (N·m about X and Z), held constant over it.
    /// A non-finite torque is treated as none (and reported by the caller).
    #[inline]
    pub fn substep(&mut self, torque: DVec2) {
        let torque = if torque.is_finite() {
            torque
        } else {
            DVec2::ZERO
        };
        let equilibrium = torque / self.stiffness;
        let [a, b, c, d] = self.propagator;
        for axis in 0..2 {
            let x = self.angle[axis] - equilibrium[axis];
            let v = self.velocity[axis];
            self.angle[axis] = equilibrium[axis] + a * x + b * v;
            self.velocity[axis] = c * x + d * v;
        }
    }

    /// The tilt as a rotation about the base, capped at `MAX_TILT` so a violent gust
    /// bends a plant over but never through the ground.
    pub fn tilt(&self) -> Quat {
        let axis = Vec3::new(self.angle.x as f32, 0.0, self.angle.y as f32);
        let length = axis.length();
        if !(length.is_finite() && length > 0.0) {
            return Quat::IDENTITY;
        }
        Quat::from_scaled_axis(axis * (length.min(MAX_TILT) / length))
    }
}

/// Largest tilt shown, radians (about 69°).
pub const MAX_TILT: f32 = 1.2;

/// `exp(A h)` for `A = [[0, 1], [−ω², −γ]]` (ω² = k/I, γ = c/I), by scaling and squaring
/// a Taylor series: exact to rounding for any ω h.
fn propagator(omega2: f64, gamma: f64, h: f64) -> [f64; 4] {
    let m = [0.0, h, -omega2 * h, -gamma * h];
    let norm = m.iter().map(|v| v.abs()).fold(0.0, f64::max);
    let squarings = if norm > 0.25 {
        (norm / 0.25).log2().ceil() as i32
    } else {
        0
    };
    let scale = 0.5f64.powi(squarings);
    let s = m.map(|v| v * scale);
    let mul = |p: [f64; 4], q: [f64; 4]| {
        [
            p[0] * q[0] + p[1] * q[2],
            p[0] * q[1] + p[1] * q[3],
            p[2] * q[0] + p[3] * q[2],
            p[2] * q[1] + p[3] * q[3],
        ]
    };
    // Taylor to degree 12: the truncation error at ‖s‖ ≤ 0.25 is below 1e-16.
    let mut result = [1.0, 0.0, 0.0, 1.0];
    let mut term = [1.0, 0.0, 0.0, 1.0];
    for n in 1..=12 {
        term = mul(term, s).map(|v| v / n as f64);
        for i in 0..4 {
            result[i] += term[i];
        }
    }
    for _ in 0..squarings {
        result = mul(result, result);
    }
    result
}

/// A gusty wind: a base speed along `direction` modulated by travelling gusts.
#[derive(Resource, Clone, Copy, Debug, PartialEq)]
pub struct Wind {
    /// Horizontal direction the wind blows toward (x, z); need not be unit length.
    pub direction: Vec2,
    /// Mean speed, m/s.
    pub speed: f32,
    /// Gust strength as a fraction of the mean speed.
    pub gustiness: f32,
    /// Gust frequency, Hz.
    pub gust_frequency: f32,
    /// Gust wavelength along the wind, m (gusts travel across the field).
    pub gust_wavelength: f32,
    /// Multiplies every torque (a one-frame gust test sets it to 1000).
    pub strength: f32,
    /// Turbulence: gusts that also vary across the wind, as a fraction of the mean
    /// speed (0: the gust fronts are straight lines).
    pub turbulence: f32,
    /// Seed of the turbulence's pattern: the same seed blows the same way.
    pub seed: u64,
}

impl Default for Wind {
    fn default() -> Self {
        Self {
            direction: Vec2::X,
            speed: 4.0,
            gustiness: 0.5,
            gust_frequency: 0.3,
            gust_wavelength: 25.0,
            strength: 1.0,
            turbulence: 0.0,
            seed: 0,
        }
    }
}

impl Wind {
    /// True when every field is finite (a wind with NaN or ∞ is ignored).
    pub fn is_finite(&self) -> bool {
        self.direction.is_finite()
            && [
                self.speed,
                self.gustiness,
                self.gust_frequency,
                self.gust_wavelength,
                self.strength,
                self.turbulence,
            ]
            .iter()
            .all(|v| v.is_finite())
    }

    /// Wind velocity (x, z) at horizontal position `p` and time `t` seconds.
    pub fn velocity(&self, p: Vec2, t: f64) -> DVec2 {
        let dir = self.direction.normalize_or_zero().as_dvec2();
        let along = dir.dot(p.as_dvec2());
        let wavelength = f64::from(self.gust_wavelength.max(1e-3));
        let phase =
            std::f64::consts::TAU * (f64::from(self.gust_frequency) * t - along / wavelength);
        let mut gust = 1.0 + f64::from(self.gustiness) * (phase.sin() + 0.5 * (2.7 * phase).sin());
        if self.turbulence != 0.0 {
            // Two waves across the wind at incommensurate rates, their phases and angles
            // from the seed: gust fronts that bend and break up.
            let across = DVec2::new(-dir.y, dir.x).dot(p.as_dvec2());
            let unit = |k: u64| {
                (crate::util::sampling::mix64(self.seed ^ k.wrapping_mul(0x9e37_79b9_7f4a_7c15))
                    >> 11) as f64
                    / (1u64 << 53) as f64
            };
            let wave = |k: u64, rate: f64| {
                let angle = (unit(2 * k) - 0.5) * std::f64::consts::PI;
                let offset = std::f64::consts::TAU * unit(2 * k + 1);
                let position = (along * angle.sin() + across * angle.cos()) / wavelength;
                (std::f64::consts::TAU * (rate * f64::from(self.gust_frequency) * t - position)
                    + offset)
                    .sin()
            };
            gust += f64::from(self.turbulence) * 0.5 * (wave(1, 1.37) + wave(2, 2.11));
        }
        dir * f64::from(self.speed) * gust.max(0.0)
    }

    /// Torque (about X, about Z) on a plant with `wind_gain` at `p`: the drag ∝ v|v| tilts
    /// it downwind (a wind toward +X turns it about −Z, toward +Z about +X).
    pub fn torque(&self, wind_gain: f64, p: Vec2, t: f64) -> DVec2 {
        let v = self.velocity(p, t);
        let drag = v * v.length() * wind_gain * f64::from(self.strength);
        DVec2::new(drag.y, -drag.x)
    }
}

/// Where a swaying plant is at rest (its `Transform` is recomputed from this each frame).
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct RestPose(pub crate::components::Transform);

/// The animation clock: seconds of simulated time and sub-steps taken.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq)]
pub struct AnimationClock {
    /// Frame time to advance by on the next `animate` run, seconds.
    pub frame_seconds: f64,
    /// Simulated time after the sub-steps taken so far.
    pub time: f64,
    /// Sub-steps taken.
    pub substeps: u64,
    /// Frame time not yet covered by a whole sub-step.
    pub carry: f64,
    /// Sub-steps taken before the latest [`advance`](Self::advance).
    pub latest_from: u64,
}

impl AnimationClock {
    /// Takes the whole sub-steps that fit in `frame_seconds` plus the carry; returns the
    /// simulated times at which each starts.
    pub fn advance(&mut self) -> Vec<f64> {
        let available = self.carry + self.frame_seconds.max(0.0);
        // A tiny tolerance so 1/30 s holds exactly 8 sub-steps of 1/240 s.
        let count = ((available / SUBSTEP) + 1e-9).floor().max(0.0) as u64;
        self.carry = (available - count as f64 * SUBSTEP).max(0.0);
        let times = (0..count)
            .map(|i| (self.substeps + i) as f64 * SUBSTEP)
            .collect();
        self.latest_from = self.substeps;
        self.substeps += count;
        self.time = self.substeps as f64 * SUBSTEP;
        times
    }

    /// The start times of the sub-steps the latest [`advance`](Self::advance) took.
    pub fn latest_times(&self) -> Vec<f64> {
        (self.latest_from..self.substeps)
            .map(|i| i as f64 * SUBSTEP)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Energy at a displaced start, then after each sub-step, no wind.
    fn energies(mut sway: Sway, steps: usize) -> Vec<f64> {
        sway.angle = DVec2::new(0.3, -0.2);
        sway.velocity = DVec2::new(0.5, 0.0);
        let start = sway.energy();
        std::iter::once(start)
            .chain((0..steps).map(|_| {
                sway.substep(DVec2::ZERO);
                sway.energy()
            }))
            .collect()
    }

    #[test]
    fn stiff_springs_decay_monotonically_without_nan() {
        for stiffness_ratio in [11.0, 1e6, 1e12] {
            // k h² / I = stiffness_ratio.
            let inertia = 2.0;
            let k = stiffness_ratio * inertia / (SUBSTEP * SUBSTEP);
            let sway = Sway::new(k, 0.05 * (k * inertia).sqrt(), inertia, 1.0).unwrap();
            let e = energies(sway, 2000);
            assert!(e.iter().all(|v| v.is_finite()), "{stiffness_ratio}");
            assert!(
                e.windows(2).all(|w| w[1] <= w[0] * (1.0 + 1e-12)),
                "energy must never grow at k h²/I = {stiffness_ratio}"
            );
            assert!(e.last().unwrap() < &e[0], "{stiffness_ratio}: it decays");
        }
    }

    #[test]
    fn undamped_energy_stays_bounded_over_a_million_steps() {
        // ω h = 0.05.
        let inertia = 1.5;
        let omega = 0.05 / SUBSTEP;
        let sway = Sway::new(omega * omega * inertia, 0.0, inertia, 1.0).unwrap();
        let e = energies(sway, 1_000_000);
        let (lo, hi) = e
            .iter()
            .fold((f64::MAX, 0f64), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        assert!((hi - lo) / e[0] < 1e-9, "energy drifted from {lo} to {hi}");
    }

    #[test]
    fn the_propagator_matches_the_analytic_oscillator() {
        let (omega, gamma) = (7.0f64, 0.8f64);
        let p = propagator(omega * omega, gamma, 0.01);
        // Underdamped: x(t) = e^{−γt/2}(cos ω_d t + γ/(2ω_d) sin ω_d t) for x0 = 1, v0 = 0.
        let wd = (omega * omega - gamma * gamma / 4.0).sqrt();
        let t = 0.01;
        let x = (-gamma * t / 2.0).exp() * ((wd * t).cos() + gamma / (2.0 * wd) * (wd * t).sin());
        assert!((p[0] - x).abs() < 1e-14, "{} vs {x}", p[0]);
    }

    #[test]
    fn bad_parameters_are_refused() {
        assert!(Sway::new(0.0, 1.0, 1.0, 1.0).is_err());
        assert!(Sway::new(1.0, -1.0, 1.0, 1.0).is_err());
        assert!(Sway::new(1.0, 1.0, f64::NAN, 1.0).is_err());
        let mut sway = Sway::new(10.0, 1.0, 1.0, 1.0).unwrap();
        sway.substep(DVec2::new(f64::NAN, 1.0));
        assert!(sway.angle.is_finite() && sway.velocity.is_finite());
        assert_eq!(sway.angle, DVec2::ZERO, "a NaN torque is no torque");
    }

    #[test]
    fn the_clock_takes_whole_substeps_and_carries_the_rest() {
        let mut clock = AnimationClock {
            frame_seconds: 1.0 / 30.0,
            ..Default::default()
        };
        assert_eq!(clock.advance().len(), 8);
        clock.frame_seconds = 0.01;
        let n = clock.advance().len();
        assert_eq!(n, 2);
        assert!((clock.carry - (0.01 - 2.0 * SUBSTEP)).abs() < 1e-12);
    }

    #[test]
    fn turbulence_varies_the_wind_across_it_by_its_seed_and_is_off_by_default() {
        let calm = Wind::default();
        // Without turbulence the gust fronts are straight: the same speed anywhere across
        // the wind (here along z for a wind toward +x).
        for z in [-30.0, 0.0, 17.0] {
            assert_eq!(
                calm.velocity(Vec2::new(5.0, z), 2.5),
                calm.velocity(Vec2::new(5.0, 0.0), 2.5)
            );
        }
        let turbulent = |seed| Wind {
            turbulence: 0.6,
            seed,
            ..Wind::default()
        };
        let across: Vec<f64> = (0..20)
            .map(|i| turbulent(7).velocity(Vec2::new(5.0, i as f32 * 3.0), 2.5).x)
            .collect();
        let spread = across.iter().copied().fold(f64::MIN, f64::max)
            - across.iter().copied().fold(f64::MAX, f64::min);
        assert!(spread > 0.5, "{across:?}");
        let p = Vec2::new(12.0, -4.0);
        assert_eq!(turbulent(7).velocity(p, 1.0), turbulent(7).velocity(p, 1.0));
        assert_ne!(turbulent(7).velocity(p, 1.0), turbulent(8).velocity(p, 1.0));
        // Never blowing backwards.
        for i in 0..200 {
            let v = turbulent(3).velocity(Vec2::new(i as f32, (i * 7 % 50) as f32), i as f64 * 0.1);
            assert!(v.x >= 0.0 && v.is_finite());
        }
    }
}
