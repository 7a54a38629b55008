//! Mock drives in the spirit of ros2_control's `mock_components`: they follow commands with a
//! configurable response and delay, report encoder noise, and let a test inject faults.
//!
//! Time only moves in [`MockDrive::step`] (or [`Drive::sync`], one period), and the noise comes
//! from a seeded ChaCha stream, so a test run is exactly reproducible and takes no wall time.

use std::collections::VecDeque;
use std::time::Duration;

use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::{check_finite, ArmDrive, Drive, HalError, JointReading, Quantity, WheelDrive};

/// Integration sub-step: small against any sensible time constant, so PD stays stable.
const SUBSTEP: Duration = Duration::from_millis(1);

/// How a joint follows its target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Response {
    /// Mirrors the command at once, like `mock_components::GenericSystem`.
    Ideal,
    /// Exponential approach to the target (velocity for velocity commands, position for
    /// position commands).
    FirstOrder { time_constant_s: f64 },
    /// A second-order joint: acceleration `kp·(q*−q) − kd·q̇` for position targets,
    /// `kp·(v*−q̇)` for velocity targets.
    Pd { kp_per_s2: f64, kd_per_s: f64 },
}

/// Mock behaviour; plain data so a test states all of it in one literal.
#[derive(Debug, Clone, PartialEq)]
pub struct MockConfig {
    pub response: Response,
    /// Time from `command_*` until the joint starts following it.
    pub command_delay: Duration,
    /// Standard deviation of the Gaussian noise added to reported positions, rad.
    pub noise_std_rad: f64,
    /// Joint-side inertia, kg·m²; when set, readings report effort = inertia · acceleration.
    pub inertia_kgm2: Option<f64>,
    /// The control period one [`Drive::sync`] advances.
    pub period: Duration,
    /// Seed of the noise stream.
    pub seed: u64,
}

impl MockConfig {
    /// A noiseless, delay-free mirror of the commands.
    pub fn ideal(period: Duration) -> Self {
        MockConfig {
            response: Response::Ideal,
            command_delay: Duration::ZERO,
            noise_std_rad: 0.0,
            inertia_kgm2: None,
            period,
            seed: 0,
        }
    }
}

/// A fault a test injects; joint indices are in the driver's joint order.
#[derive(Debug, Clone, PartialEq)]
pub enum MockFault {
    /// The joint stops moving whatever it is commanded.
    Stuck { joint: usize },
    /// Reads fail with [`HalError::NoFeedback`] for this joint.
    EncoderDropout { joint: usize },
    /// The drive latches a fault and drops torque until `reset_fault` and `enable`.
    DriveFault { joint: usize, reason: String },
    /// Commands issued in the next `duration` take `extra` longer to arrive (and queue the
    /// ones behind them).
    LatencySpike { extra: Duration, duration: Duration },
    /// Every call fails with [`HalError::Bus`] until [`MockDrive::heal`].
    BusLost,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Target<const N: usize> {
    Velocity([f64; N]),
    Position([f64; N]),
}

/// N mock joints; a `MockDrive<2>` is a [`WheelDrive`], a `MockDrive<7>` an [`ArmDrive`].
pub struct MockDrive<const N: usize> {
    names: [String; N],
    config: MockConfig,
    rng: ChaCha8Rng,
    now: Duration,
    position_rad: [f64; N],
    velocity_radps: [f64; N],
    effort_nm: [f64; N],
    /// `None` holds still: velocity 0 at the current position.
    target: Option<Target<N>>,
    /// Commands in flight, with the time they arrive; FIFO like a bus.
    in_flight: VecDeque<(Duration, Target<N>)>,
    enabled: bool,
    fault: Option<HalError>,
    stuck: [bool; N],
    /// Per joint: since when its encoder is silent.
    dropout_since: [Option<Duration>; N],
    spike_until: Duration,
    spike_extra: Duration,
    bus_lost: bool,
}

impl<const N: usize> MockDrive<N> {
    /// A disabled drive at rest at zero.
    pub fn new(names: [String; N], config: MockConfig) -> Self {
        MockDrive {
            names,
            rng: ChaCha8Rng::seed_from_u64(config.seed),
            config,
            now: Duration::ZERO,
            position_rad: [0.0; N],
            velocity_radps: [0.0; N],
            effort_nm: [0.0; N],
            target: None,
            in_flight: VecDeque::new(),
            enabled: false,
            fault: None,
            stuck: [false; N],
            dropout_since: [None; N],
            spike_until: Duration::ZERO,
            spike_extra: Duration::ZERO,
            bus_lost: false,
        }
    }

    /// Places the joints (the hardware's state at power-on), at rest.
    pub fn set_position(&mut self, position_rad: &[f64; N]) {
        self.position_rad = *position_rad;
        self.velocity_radps = [0.0; N];
    }

    /// Simulated time since creation.
    pub fn now(&self) -> Duration {
        self.now
    }

    pub fn inject(&mut self, fault: MockFault) {
        match fault {
            MockFault::Stuck { joint } => self.stuck[joint] = true,
            MockFault::EncoderDropout { joint } => self.dropout_since[joint] = Some(self.now),
            MockFault::DriveFault { joint, reason } => {
                self.fault = Some(HalError::DriveFault {
                    joint: self.names[joint].clone(),
                    reason,
                });
                self.enabled = false;
            }
            MockFault::LatencySpike { extra, duration } => {
                self.spike_extra = extra;
                self.spike_until = self.now + duration;
            }
            MockFault::BusLost => self.bus_lost = true,
        }
    }

    /// Clears stuck joints, encoder dropouts, latency spikes and a lost bus; a latched drive
    /// fault still needs [`Drive::reset_fault`], as on real hardware.
    pub fn heal(&mut self) {
        self.stuck = [false; N];
        self.dropout_since = [None; N];
        self.spike_until = self.now;
        self.bus_lost = false;
    }

    /// Advances simulated time by `dt`.
    pub fn step(&mut self, dt: Duration) {
        let start_velocity = self.velocity_radps;
        let end = self.now + dt;
        while self.now < end {
            let h = SUBSTEP.min(end - self.now);
            while let Some(&(arrival, target)) = self.in_flight.front() {
                if arrival > self.now {
                    break;
                }
                self.in_flight.pop_front();
                if self.enabled {
                    self.target = Some(target);
                }
            }
            self.integrate(h.as_secs_f64());
            self.now += h;
        }
        let dt_s = dt.as_secs_f64();
        self.effort_nm = match self.config.inertia_kgm2 {
            Some(inertia) if dt_s > 0.0 => std::array::from_fn(|i| {
                inertia * (self.velocity_radps[i] - start_velocity[i]) / dt_s
            }),
            _ => [0.0; N],
        };
    }

    fn integrate(&mut self, h: f64) {
        let target = if self.enabled { self.target } else { None };
        for i in 0..N {
            if self.stuck[i] {
                self.velocity_radps[i] = 0.0;
                continue;
            }
            let (q, v) = (self.position_rad[i], self.velocity_radps[i]);
            let (q, v) = match (target, self.config.response) {
                (None, _) => (q, 0.0),
                (Some(Target::Velocity(t)), Response::Ideal) => (q + t[i] * h, t[i]),
                (Some(Target::Position(t)), Response::Ideal) => (t[i], 0.0),
                (Some(Target::Velocity(t)), Response::FirstOrder { time_constant_s }) => {
                    let v = v + (t[i] - v) * (1.0 - (-h / time_constant_s).exp());
                    (q + v * h, v)
                }
                (Some(Target::Position(t)), Response::FirstOrder { time_constant_s }) => {
                    let next = q + (t[i] - q) * (1.0 - (-h / time_constant_s).exp());
                    (next, (next - q) / h)
                }
                (Some(Target::Velocity(t)), Response::Pd { kp_per_s2, .. }) => {
                    let v = v + kp_per_s2 * (t[i] - v) * h;
                    (q + v * h, v)
                }
                (
                    Some(Target::Position(t)),
                    Response::Pd {
                        kp_per_s2,
                        kd_per_s,
                    },
                ) => {
                    let v = v + (kp_per_s2 * (t[i] - q) - kd_per_s * v) * h;
                    (q + v * h, v)
                }
            };
            self.position_rad[i] = q;
            self.velocity_radps[i] = v;
        }
    }

    fn bus_error(&self) -> HalError {
        HalError::Bus {
            bus: "mock".to_owned(),
            reason: "bus lost (injected)".to_owned(),
        }
    }

    /// Fails on a lost bus or a latched fault: shared by every call that talks to the drive.
    fn check_alive(&self) -> Result<(), HalError> {
        if self.bus_lost {
            return Err(self.bus_error());
        }
        self.fault.clone().map_or(Ok(()), Err)
    }

    fn command(
        &mut self,
        target: Target<N>,
        values: &[f64; N],
        quantity: Quantity,
    ) -> Result<(), HalError> {
        self.check_alive()?;
        if !self.enabled {
            return Err(HalError::NotEnabled {
                joint: self.names[0].clone(),
            });
        }
        check_finite(&self.names, values, quantity)?;
        let spike = if self.now < self.spike_until {
            self.spike_extra
        } else {
            Duration::ZERO
        };
        let arrival = self.now + self.config.command_delay + spike;
        self.in_flight.push_back((arrival, target));
        Ok(())
    }

    fn read(&mut self) -> Result<JointReading<N>, HalError> {
        if self.bus_lost {
            return Err(self.bus_error());
        }
        if let Some((joint, since)) = self
            .dropout_since
            .iter()
            .enumerate()
            .find_map(|(i, since)| since.map(|s| (i, s)))
        {
            return Err(HalError::NoFeedback {
                joint: self.names[joint].clone(),
                waited: self.now - since,
            });
        }
        let std = self.config.noise_std_rad;
        let noise = Normal::new(0.0, std).ok().filter(|_| std > 0.0);
        let mut position_rad = self.position_rad;
        if let Some(noise) = noise {
            for q in &mut position_rad {
                *q += noise.sample(&mut self.rng);
            }
        }
        Ok(JointReading {
            position_rad,
            velocity_radps: self.velocity_radps,
            effort_nm: self.config.inertia_kgm2.map(|_| self.effort_nm),
            stamp: self.now,
        })
    }
}

impl<const N: usize> Drive for MockDrive<N> {
    fn enable(&mut self) -> Result<(), HalError> {
        self.check_alive()?;
        self.enabled = true;
        self.target = None;
        Ok(())
    }

    fn disable(&mut self) -> Result<(), HalError> {
        if self.bus_lost {
            return Err(self.bus_error());
        }
        self.enabled = false;
        self.target = None;
        self.in_flight.clear();
        Ok(())
    }

    fn fault(&self) -> Option<HalError> {
        self.check_alive().err()
    }

    fn reset_fault(&mut self) -> Result<(), HalError> {
        if self.bus_lost {
            return Err(self.bus_error());
        }
        self.fault = None;
        self.enabled = false;
        Ok(())
    }

    fn sync(&mut self) -> Result<(), HalError> {
        if self.bus_lost {
            return Err(self.bus_error());
        }
        self.step(self.config.period);
        self.check_alive()
    }
}

impl WheelDrive for MockDrive<WHEEL_JOINTS> {
    fn command_velocity(&mut self, velocity_radps: &[f64; WHEEL_JOINTS]) -> Result<(), HalError> {
        self.command(
            Target::Velocity(*velocity_radps),
            velocity_radps,
            Quantity::Velocity,
        )
    }

    fn read_wheels(&mut self) -> Result<JointReading<WHEEL_JOINTS>, HalError> {
        self.read()
    }
}

impl ArmDrive for MockDrive<ARM_JOINTS> {
    fn command_position(&mut self, position_rad: &[f64; ARM_JOINTS]) -> Result<(), HalError> {
        self.command(
            Target::Position(*position_rad),
            position_rad,
            Quantity::Position,
        )
    }

    fn read_arm(&mut self) -> Result<JointReading<ARM_JOINTS>, HalError> {
        self.read()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: Duration = Duration::from_millis(20);

    fn arm_names() -> [String; ARM_JOINTS] {
        std::array::from_fn(|i| format!("arm{i}"))
    }

    fn arm(config: MockConfig) -> MockDrive<ARM_JOINTS> {
        let mut arm = MockDrive::new(arm_names(), config);
        arm.enable().unwrap();
        arm
    }

    fn first_order(tau: f64) -> MockConfig {
        MockConfig {
            response: Response::FirstOrder {
                time_constant_s: tau,
            },
            ..MockConfig::ideal(PERIOD)
        }
    }

    #[test]
    fn first_order_reaches_63_percent_after_one_time_constant() {
        let mut arm = arm(first_order(0.1));
        arm.command_position(&[1.0; ARM_JOINTS]).unwrap();
        for _ in 0..5 {
            arm.sync().unwrap();
        }
        let q = arm.read_arm().unwrap();
        assert!((q.position_rad[0] - (1.0 - (-1.0f64).exp())).abs() < 1e-9);
        assert_eq!(q.stamp, Duration::from_millis(100));
    }

    #[test]
    fn pd_response_settles_on_the_target() {
        let mut arm = arm(MockConfig {
            response: Response::Pd {
                kp_per_s2: 400.0,
                kd_per_s: 40.0,
            },
            ..MockConfig::ideal(PERIOD)
        });
        arm.command_position(&[0.5; ARM_JOINTS]).unwrap();
        arm.step(Duration::from_secs(2));
        let q = arm.read_arm().unwrap();
        assert!((q.position_rad[6] - 0.5).abs() < 1e-4);
        assert!(q.velocity_radps[6].abs() < 1e-3);
    }

    #[test]
    fn wheels_track_velocity_and_integrate_position() {
        let names = ["left".to_owned(), "right".to_owned()];
        let mut wheels = MockDrive::new(names, MockConfig::ideal(PERIOD));
        assert!(matches!(
            wheels.command_velocity(&[1.0, 1.0]),
            Err(HalError::NotEnabled { .. })
        ));
        wheels.enable().unwrap();
        wheels.command_velocity(&[1.0, -2.0]).unwrap();
        wheels.step(Duration::from_secs(1));
        let r = wheels.read_wheels().unwrap();
        assert_eq!(r.velocity_radps, [1.0, -2.0]);
        assert!((r.position_rad[0] - 1.0).abs() < 1e-9);
        assert!((r.position_rad[1] + 2.0).abs() < 1e-9);
        assert_eq!(r.effort_nm, None);
    }

    #[test]
    fn command_delay_and_latency_spike_postpone_motion() {
        let mut arm = arm(MockConfig {
            command_delay: Duration::from_millis(30),
            ..MockConfig::ideal(PERIOD)
        });
        arm.command_position(&[1.0; ARM_JOINTS]).unwrap();
        arm.sync().unwrap();
        assert_eq!(arm.read_arm().unwrap().position_rad[0], 0.0);
        arm.sync().unwrap();
        assert_eq!(arm.read_arm().unwrap().position_rad[0], 1.0);

        arm.inject(MockFault::LatencySpike {
            extra: Duration::from_millis(100),
            duration: Duration::from_millis(10),
        });
        arm.command_position(&[2.0; ARM_JOINTS]).unwrap(); // arrives at 40 + 30 + 100 ms
        for _ in 0..6 {
            arm.sync().unwrap();
        }
        assert_eq!(arm.read_arm().unwrap().position_rad[0], 1.0);
        arm.sync().unwrap();
        assert_eq!(arm.read_arm().unwrap().position_rad[0], 2.0);
    }

    #[test]
    fn noise_is_deterministic_for_a_seed() {
        let noisy = |seed| {
            let mut arm = arm(MockConfig {
                noise_std_rad: 0.01,
                seed,
                ..MockConfig::ideal(PERIOD)
            });
            (0..50)
                .map(|_| arm.read_arm().unwrap().position_rad[0])
                .collect::<Vec<_>>()
        };
        let a = noisy(7);
        assert_eq!(a, noisy(7));
        assert_ne!(a, noisy(8));
        let mean = a.iter().sum::<f64>() / a.len() as f64;
        let std = (a.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / a.len() as f64).sqrt();
        assert!(std > 0.005 && std < 0.02, "std {std}");
    }

    #[test]
    fn injected_faults_are_reported_by_joint() {
        let mut arm = arm(MockConfig::ideal(PERIOD));
        arm.inject(MockFault::Stuck { joint: 2 });
        arm.command_position(&[1.0; ARM_JOINTS]).unwrap();
        arm.sync().unwrap();
        let q = arm.read_arm().unwrap().position_rad;
        assert_eq!((q[1], q[2]), (1.0, 0.0));

        arm.inject(MockFault::EncoderDropout { joint: 4 });
        arm.sync().unwrap();
        let err = arm.read_arm().unwrap_err();
        assert_eq!(
            err,
            HalError::NoFeedback {
                joint: "arm4".into(),
                waited: PERIOD
            }
        );
        arm.heal();
        assert!(arm.read_arm().is_ok());

        arm.inject(MockFault::DriveFault {
            joint: 5,
            reason: "overcurrent".into(),
        });
        let err = arm.sync().unwrap_err();
        assert!(matches!(err, HalError::DriveFault { ref joint, .. } if joint == "arm5"));
        assert_eq!(arm.fault(), Some(err.clone()));
        assert_eq!(arm.command_position(&[0.0; ARM_JOINTS]), Err(err));
        arm.reset_fault().unwrap();
        assert!(matches!(
            arm.command_position(&[0.0; ARM_JOINTS]),
            Err(HalError::NotEnabled { .. })
        ));
        arm.enable().unwrap();
        arm.command_position(&[0.0; ARM_JOINTS]).unwrap();

        arm.inject(MockFault::BusLost);
        assert!(matches!(arm.sync(), Err(HalError::Bus { .. })));
        assert!(matches!(arm.read_arm(), Err(HalError::Bus { .. })));
        assert!(matches!(arm.fault(), Some(HalError::Bus { .. })));
        arm.heal();
        assert_eq!(arm.fault(), None);
    }
}
