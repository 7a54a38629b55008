//! Domain randomization (paper, Sec. VI-A): wheel–ground friction μ ~ U(0.6, 1.0), terrain
//! perturbations (see [`crate::terrain`]), wheel command noise N(0, 0.05²) rad/s, arm command
//! noise N(0, 0.01²) rad, initial joint variation, payload choice and mass.
//!
//! The paper gives no number for the initial joint variation; we draw each arm joint's offset
//! from U(−δ, δ) with δ = 0.02 rad (≈ 1 cm at the end effector) so grasps start slightly
//! asymmetric. Payload mass is scaled by U(lo, hi), 1 by default: the payload choice already
//! spans the paper's masses.
//!
//! Every draw comes from the env's own [`ChaCha8Rng`], so an env's episode depends on its seed
//! only, never on which thread steps it.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::terrain::TerrainRandomization;
use crate::SimError;
use moonhaul_core::config::{count, in_range, interval, section, FieldError};
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};

/// The payloads of the paper, and one loaded from a URDF file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PayloadKind {
    /// Cargo box, 7.5 kg.
    Box,
    /// Cargo box with bricks, 9.5 kg.
    Bricks,
    /// Sledge, 5.3 kg, elongated; unseen in the paper's training.
    Sledge,
    /// The payload a scene loaded from a URDF file
    /// ([`crate::SceneModel::add_payload_file`]). Set only in code: a config naming it is
    /// refused, since a config cannot say which file it means.
    #[serde(skip_deserializing)]
    Custom,
    /// Member `i` of the scene's generated family ([`GeneratedPayloads`]): a box of drawn size,
    /// mass and centre of mass, the same for every scene built from the same config. Named
    /// `gen<i>` on the command line; in configs only through `[randomization.generated_payloads]`.
    Generated(u8),
}

impl PayloadKind {
    /// The shipped payloads (`assets/payload_<name>.urdf`); never [`PayloadKind::Custom`].
    pub const ALL: [PayloadKind; 3] = [PayloadKind::Box, PayloadKind::Bricks, PayloadKind::Sledge];

    /// The name used in configs, CLI flags and asset file names; `custom` for a payload file,
    /// which [`crate::SceneModel::payload_name`] names by its file instead.
    pub fn name(self) -> &'static str {
        match self {
            PayloadKind::Box => "box",
            PayloadKind::Bricks => "bricks",
            PayloadKind::Sledge => "sledge",
            PayloadKind::Custom => "custom",
            PayloadKind::Generated(_) => "generated",
        }
    }
}

impl PayloadKind {
    /// The name a shipped or generated payload is given on the command line and in reports
    /// (`gen<i>` for a generated one), what [`std::str::FromStr`] parses back.
    pub fn label(self) -> String {
        match self {
            PayloadKind::Generated(i) => format!("gen{i}"),
            other => other.name().into(),
        }
    }
}

/// Parses a shipped payload's name or a generated payload's (`gen<i>`, which a scene then
/// checks it has); `custom` names no file.
impl std::str::FromStr for PayloadKind {
    type Err = SimError;

    fn from_str(s: &str) -> Result<Self, SimError> {
        if let Some(i) = s.strip_prefix("gen").and_then(|i| i.parse::<u8>().ok()) {
            return Ok(PayloadKind::Generated(i));
        }
        PayloadKind::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| SimError::Config {
                field: "payload",
                reason: format!(
                    "unknown payload {s:?} (expected box, bricks, sledge or gen<i>, a generated \
                     payload)"
                ),
            })
    }
}

/// A family of box payloads the scene generates at build time (not in the paper): training on
/// the paper's two crates alone taught the lift one grasp height, and a lift policy cloned on
/// them never lifted the sledge or any other crate (docs/measurements/2026-12-04.md). The
/// family spans sizes, masses and centre-of-mass offsets around the shipped payloads, so a
/// policy sees many grasp heights, loads and tilting moments; the shipped payloads and the
/// test crates stay out of it (a draw is continuous, they are single points). Drawn from `seed`
/// alone, so every scene built from one config holds the same family (a hand-over start names
/// its member and is replayed in another process).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeneratedPayloads {
    /// Members of the family, 0 to 64 (0: none).
    pub count: u8,
    /// The family's draws come from this seed only.
    pub seed: u64,
    /// Probability that a world carries a member of the family rather than one of `payloads`.
    pub share: f64,
    /// Box size ranges along x (travel), y (between the grasps) and z, m; uniform. Every x
    /// is at least every y (the long side along x, as the payload convention asks).
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub size_x_m: [f64; 2],
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub size_y_m: [f64; 2],
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub size_z_m: [f64; 2],
    /// Mass range, kg; uniform. The inertia is the solid box's.
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub mass_kg: [f64; 2],
    /// Largest centre-of-mass offset from the box centre along x, y, z, m; each uniform in
    /// ±this (at most a third of the smallest half size).
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub com_offset_m: [f64; 3],
}

/// One generated payload: its box, mass and centre of mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeneratedPayload {
    pub size_m: [f64; 3],
    pub mass_kg: f64,
    pub com_m: [f64; 3],
}

impl GeneratedPayload {
    /// The payload as a URDF (the payload convention of [`crate::scene`]), so a generated
    /// payload passes every check a payload file does.
    pub fn urdf(&self, name: &str) -> String {
        let [x, y, z] = self.size_m;
        let m = self.mass_kg;
        let [cx, cy, cz] = self.com_m;
        let (ixx, iyy, izz) = (
            m * (y * y + z * z) / 12.0,
            m * (x * x + z * z) / 12.0,
            m * (x * x + y * y) / 12.0,
        );
        format!(
            "<?xml version=\"1.0\"?>\n<robot name=\"{name}\">\n  <link name=\"payload\">\n    \
             <inertial>\n      <origin xyz=\"{cx} {cy} {cz}\" rpy=\"0 0 0\"/>\n      \
             <mass value=\"{m}\"/>\n      <inertia ixx=\"{ixx}\" ixy=\"0\" ixz=\"0\" \
             iyy=\"{iyy}\" iyz=\"0\" izz=\"{izz}\"/>\n    </inertial>\n    <collision>\n      \
             <geometry><box size=\"{x} {y} {z}\"/></geometry>\n    </collision>\n  </link>\n\
             </robot>\n"
        )
    }
}

impl GeneratedPayloads {
    fn validate(&self) -> Result<(), FieldError> {
        count("count", self.count as u64, 0, 64)?;
        in_range("share", self.share, 0.0, 1.0)?;
        interval("size_x_m", self.size_x_m, 0.05, 2.0)?;
        interval("size_y_m", self.size_y_m, 0.05, 1.0)?;
        interval("size_z_m", self.size_z_m, 0.05, 1.0)?;
        interval("mass_kg", self.mass_kg, 0.1, 100.0)?;
        if self.size_x_m[0] < self.size_y_m[1] {
            return Err(FieldError::new(
                "size_x_m",
                format!(
                    "the shortest x ({} m) must be at least the longest y ({} m): the long side \
                     lies along x",
                    self.size_x_m[0], self.size_y_m[1]
                ),
            ));
        }
        let smallest = [self.size_x_m[0], self.size_y_m[0], self.size_z_m[0]];
        for (axis, (&offset, size)) in self.com_offset_m.iter().zip(smallest).enumerate() {
            in_range("com_offset_m", offset, 0.0, size / 6.0).map_err(|e| {
                FieldError::new(
                    e.field,
                    format!("axis {}: {}", ["x", "y", "z"][axis], e.reason),
                )
            })?;
        }
        Ok(())
    }

    /// Draws one member from `rng`.
    pub fn draw(&self, rng: &mut ChaCha8Rng) -> GeneratedPayload {
        let size_m = [
            uniform(rng, self.size_x_m),
            uniform(rng, self.size_y_m),
            uniform(rng, self.size_z_m),
        ];
        let mass_kg = uniform(rng, self.mass_kg);
        let com_m = self.com_offset_m.map(|d| uniform(rng, [-d, d]));
        GeneratedPayload {
            size_m,
            mass_kg,
            com_m,
        }
    }
}

/// Ranges of every randomized term.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Randomization {
    /// Wheel–ground friction coefficient range, uniform.
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub wheel_friction: [f64; 2],
    /// Standard deviation of the Gaussian noise added to each wheel velocity command, rad/s.
    pub wheel_velocity_noise_std_radps: f64,
    /// Standard deviation of the Gaussian noise added to each arm position command, rad.
    pub arm_position_noise_std_rad: f64,
    /// Half-width of the uniform offset added to each arm joint at reset, rad.
    pub initial_joint_variation_rad: f64,
    /// Payloads drawn uniformly at reset (when the world does not carry a generated one).
    pub payloads: Vec<PayloadKind>,
    /// The generated family and how often a world carries one of its members.
    pub generated_payloads: GeneratedPayloads,
    /// Payload mass scale range, uniform.
    #[serde(deserialize_with = "moonhaul_core::config::exact_array")]
    pub payload_mass_scale: [f64; 2],
    pub terrain: TerrainRandomization,
}

/// What one episode of one env got: drawn at reset.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeDraw {
    pub payload: PayloadKind,
    pub payload_mass_scale: f64,
    pub wheel_friction: f64,
    /// Per unit, per arm joint, rad.
    pub initial_joint_offset_rad: [[f64; ARM_JOINTS]; 2],
    /// Terrain randomization for this episode; `None` for flat ground.
    pub terrain: Option<TerrainRandomization>,
}

/// Per-step command noise, drawn from the env's stream.
#[derive(Debug, Clone, Copy)]
pub struct CommandNoise {
    wheel: Option<Normal<f64>>,
    arm: Option<Normal<f64>>,
}

impl CommandNoise {
    /// Noise `(wheel rad/s, arm rad)` for one unit's command.
    pub fn sample(&self, rng: &mut ChaCha8Rng) -> ([f64; WHEEL_JOINTS], [f64; ARM_JOINTS]) {
        let mut wheel = [0.0; WHEEL_JOINTS];
        let mut arm = [0.0; ARM_JOINTS];
        if let Some(d) = self.wheel {
            wheel.iter_mut().for_each(|w| *w = d.sample(rng));
        }
        if let Some(d) = self.arm {
            arm.iter_mut().for_each(|a| *a = d.sample(rng));
        }
        (wheel, arm)
    }
}

fn uniform(rng: &mut ChaCha8Rng, [lo, hi]: [f64; 2]) -> f64 {
    if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    }
}

impl Randomization {
    /// Checks every range, relative to the `[randomization]` section; `terrain_spacing_m` is
    /// the heightfield grid the correlation lengths are resolved on.
    pub fn validate(&self, terrain_spacing_m: f64) -> Result<(), FieldError> {
        interval("wheel_friction", self.wheel_friction, 0.0, 2.0)?;
        interval("payload_mass_scale", self.payload_mass_scale, 0.1, 10.0)?;
        in_range(
            "wheel_velocity_noise_std_radps",
            self.wheel_velocity_noise_std_radps,
            0.0,
            10.0,
        )?;
        in_range(
            "arm_position_noise_std_rad",
            self.arm_position_noise_std_rad,
            0.0,
            0.5,
        )?;
        in_range(
            "initial_joint_variation_rad",
            self.initial_joint_variation_rad,
            0.0,
            0.5,
        )?;
        count("payloads", self.payloads.len() as u64, 1, 64).map_err(|e| {
            FieldError::new(
                e.field,
                format!("needs 1 to 64 entries, got {}", self.payloads.len()),
            )
        })?;
        if self
            .payloads
            .iter()
            .any(|p| matches!(p, PayloadKind::Custom | PayloadKind::Generated(_)))
        {
            return Err(FieldError::new(
                "payloads",
                "names shipped payloads only (box, bricks, sledge); generated payloads come \
                 from [randomization.generated_payloads]",
            ));
        }
        section("generated_payloads", || self.generated_payloads.validate())?;
        section("terrain", || {
            let t = &self.terrain;
            in_range("max_peak_to_peak_m", t.max_peak_to_peak_m, 0.0, 0.5)?;
            // The smoothing kernel spans ~3 correlation lengths: at most 1 m keeps it a few
            // hundred cells; at least one grid cell keeps the field resolved.
            interval(
                "correlation_length_m",
                t.correlation_length_m,
                terrain_spacing_m,
                1.0,
            )
        })
    }

    /// Draws one episode's randomization.
    pub fn draw(&self, rng: &mut ChaCha8Rng) -> EpisodeDraw {
        let listed = self.payloads[rng.random_range(0..self.payloads.len())];
        // The family's choice comes from a side stream of the world's generator (a copy on
        // another ChaCha stream), so the world's own stream — everything drawn after this —
        // is what it was before the family existed: a world with a given seed and a forced
        // payload has the same terrain, friction and noise with or without the family.
        let generated = &self.generated_payloads;
        let mut side = rng.clone();
        side.set_stream(!rng.get_stream());
        let payload = if generated.count > 0 && side.random_bool(generated.share) {
            PayloadKind::Generated(side.random_range(0..generated.count))
        } else {
            listed
        };
        let payload_mass_scale = uniform(rng, self.payload_mass_scale);
        let wheel_friction = uniform(rng, self.wheel_friction);
        let d = self.initial_joint_variation_rad;
        let mut initial_joint_offset_rad = [[0.0; ARM_JOINTS]; 2];
        for q in initial_joint_offset_rad.iter_mut().flatten() {
            *q = uniform(rng, [-d, d]);
        }
        EpisodeDraw {
            payload,
            payload_mass_scale,
            wheel_friction,
            initial_joint_offset_rad,
            terrain: Some(self.terrain),
        }
    }

    /// The per-step command noise distributions.
    pub fn command_noise(&self) -> CommandNoise {
        let normal = |std: f64| {
            (std > 0.0)
                .then(|| Normal::new(0.0, std))
                .and_then(Result::ok)
        };
        CommandNoise {
            wheel: normal(self.wheel_velocity_noise_std_radps),
            arm: normal(self.arm_position_noise_std_rad),
        }
    }

    /// The nominal episode with `payload`: mid-range friction and payload mass scale (1 with
    /// the shipped range), flat ground, no offsets.
    pub fn nominal(&self, payload: PayloadKind) -> EpisodeDraw {
        EpisodeDraw {
            payload,
            payload_mass_scale: 0.5 * (self.payload_mass_scale[0] + self.payload_mass_scale[1]),
            wheel_friction: 0.5 * (self.wheel_friction[0] + self.wheel_friction[1]),
            initial_joint_offset_rad: [[0.0; ARM_JOINTS]; 2],
            terrain: None,
        }
    }

    /// No noise at all (for `--no-randomization` runs).
    pub fn noiseless() -> CommandNoise {
        CommandNoise {
            wheel: None,
            arm: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `[randomization]` of the shipped `configs/sim.toml`: the paper's ranges.
    fn shipped() -> Randomization {
        crate::SimConfig::shipped().unwrap().randomization
    }
    use rand::SeedableRng;

    fn mean_std(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        (
            mean,
            (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
        )
    }

    /// The Kolmogorov–Smirnov critical distance at α = 0.001 for `n` samples.
    fn ks_critical(n: usize) -> f64 {
        1.95 / (n as f64).sqrt()
    }

    /// Kolmogorov–Smirnov distance of samples from U(lo, hi).
    fn ks_uniform(xs: &mut [f64], lo: f64, hi: f64) -> f64 {
        xs.sort_by(f64::total_cmp);
        let n = xs.len() as f64;
        xs.iter()
            .enumerate()
            .map(|(i, &x)| {
                let cdf = ((x - lo) / (hi - lo)).clamp(0.0, 1.0);
                (cdf - i as f64 / n)
                    .abs()
                    .max((cdf - (i + 1) as f64 / n).abs())
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn friction_joint_offsets_and_payloads_follow_their_uniform_distributions() {
        let r = Randomization {
            payloads: PayloadKind::ALL.to_vec(),
            ..shipped()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let draws: Vec<EpisodeDraw> = (0..4000).map(|_| r.draw(&mut rng)).collect();
        let mut mu: Vec<f64> = draws.iter().map(|d| d.wheel_friction).collect();
        assert!(ks_uniform(&mut mu, 0.6, 1.0) < ks_critical(mu.len()));
        let mut q: Vec<f64> = draws
            .iter()
            .flat_map(|d| d.initial_joint_offset_rad.concat())
            .collect();
        assert!(ks_uniform(&mut q, -0.02, 0.02) < ks_critical(q.len()));
        // The generated family takes its share; the listed payloads split the rest evenly.
        let rest = 1.0 - r.generated_payloads.share;
        for kind in PayloadKind::ALL {
            let share = draws.iter().filter(|d| d.payload == kind).count() as f64 / 4000.0;
            assert!((share - rest / 3.0).abs() < 0.03, "{kind:?}: {share}");
        }
        assert!(draws.iter().all(|d| d.payload_mass_scale == 1.0));
    }

    #[test]
    fn the_generated_family_leaves_the_worlds_own_stream_alone() {
        let with = shipped();
        assert!(with.generated_payloads.count > 0 && with.generated_payloads.share > 0.0);
        let mut without = with.clone();
        without.generated_payloads.count = 0;
        let (mut a, mut b) = (ChaCha8Rng::seed_from_u64(3), ChaCha8Rng::seed_from_u64(3));
        let mut generated = 0;
        for _ in 0..200 {
            let (x, y) = (with.draw(&mut a), without.draw(&mut b));
            assert_eq!(x.wheel_friction, y.wheel_friction);
            assert_eq!(x.initial_joint_offset_rad, y.initial_joint_offset_rad);
            match x.payload {
                PayloadKind::Generated(_) => generated += 1,
                p => assert_eq!(p, y.payload),
            }
            // What the world draws next (its terrain) is the same too.
            assert_eq!(a.random::<u64>(), b.random::<u64>());
        }
        assert!((60..140).contains(&generated), "{generated}");
    }

    #[test]
    fn command_noise_has_the_papers_standard_deviations() {
        let noise = shipped().command_noise();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (mut wheel, mut arm) = (Vec::new(), Vec::new());
        for _ in 0..20_000 {
            let (w, a) = noise.sample(&mut rng);
            wheel.extend(w);
            arm.extend(a);
        }
        let (wm, ws) = mean_std(&wheel);
        let (am, asd) = mean_std(&arm);
        assert!(
            wm.abs() < 0.002 && (ws - 0.05).abs() < 0.001,
            "wheel {wm} {ws}"
        );
        assert!(
            am.abs() < 0.0003 && (asd - 0.01).abs() < 0.0002,
            "arm {am} {asd}"
        );
        let none = Randomization::noiseless().sample(&mut rng);
        assert_eq!(none, ([0.0; WHEEL_JOINTS], [0.0; ARM_JOINTS]));
    }

    #[test]
    fn payload_mass_scale_is_uniform_when_configured() {
        let r = Randomization {
            payload_mass_scale: [0.8, 1.2],
            ..shipped()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut s: Vec<f64> = (0..4000)
            .map(|_| r.draw(&mut rng).payload_mass_scale)
            .collect();
        assert!(ks_uniform(&mut s, 0.8, 1.2) < ks_critical(s.len()));
    }

    #[test]
    fn terrain_amplitude_and_correlation_length_are_uniform_in_the_papers_ranges() {
        let terrain = shipped().terrain;
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (mut amplitude, mut length) = (Vec::new(), Vec::new());
        for _ in 0..2000 {
            let field = terrain.sample(8, 0.01, &mut rng).unwrap();
            amplitude.push(field.peak_to_peak_m());
            length.push(field.correlation_length_m);
        }
        assert!(ks_uniform(&mut amplitude, 0.0, 0.02) < ks_critical(amplitude.len()));
        assert!(ks_uniform(&mut length, 0.05, 0.15) < ks_critical(length.len()));
    }

    #[test]
    fn bad_ranges_are_named() {
        let r = Randomization {
            wheel_friction: [1.0, 0.6],
            ..shipped()
        };
        assert!(r
            .validate(0.025)
            .unwrap_err()
            .to_string()
            .contains("wheel_friction"));
        let r = Randomization {
            payloads: vec![],
            ..shipped()
        };
        assert!(r
            .validate(0.025)
            .unwrap_err()
            .to_string()
            .contains("payloads"));
    }
}
