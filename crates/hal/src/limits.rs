//! URDF joint limits applied as a decorator around any driver (openrr `arci` style), so no
//! driver re-implements them and a mock and a real drive are limited identically.
//!
//! Policy: position and velocity commands are either clamped or rejected ([`LimitPolicy`]);
//! the daemon clamps (the sync clamp upstream already bounds every step, so a clamp here only
//! trims numerical overshoot), tests and bring-up reject to surface planner bugs. An effort
//! reading beyond the URDF effort limit is always an error: a measurement cannot be clamped.
//! Arm velocity limits bound the step between consecutive position commands over one period.

use moonhaul_core::kinematics::JointLimits;
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::UnitSpec;
use std::time::Duration;

use crate::{check_finite, ArmDrive, Drive, HalError, JointReading, Quantity, WheelDrive};

/// What to do with a command outside the limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitPolicy {
    /// Move the command to the nearest admissible value.
    Clamp,
    /// Fail with [`HalError::OutOfLimits`] naming the joint.
    Reject,
}

/// Limits of N driven joints, in the driver's joint order.
#[derive(Debug, Clone, PartialEq)]
pub struct JointLimitSet<const N: usize> {
    pub names: [String; N],
    pub limits: [JointLimits; N],
}

impl JointLimitSet<WHEEL_JOINTS> {
    /// The wheels' limits from the unit's URDF, left then right.
    pub fn wheels(spec: &UnitSpec) -> Self {
        JointLimitSet {
            names: spec.wheel_joints.clone(),
            limits: spec.wheel_limits,
        }
    }
}

impl JointLimitSet<ARM_JOINTS> {
    /// The arm joints' limits from the unit's URDF, base to tip.
    pub fn arm(spec: &UnitSpec) -> Self {
        JointLimitSet {
            names: spec.arm_joints.clone(),
            limits: spec.arm_limits,
        }
    }
}

impl<const N: usize> JointLimitSet<N> {
    /// Applies `policy` to `values`, each within `[bound(l).0, bound(l).1]`.
    fn apply(
        &self,
        policy: LimitPolicy,
        quantity: Quantity,
        values: &mut [f64; N],
        bound: impl Fn(usize, &JointLimits) -> (f64, f64),
    ) -> Result<(), HalError> {
        check_finite(&self.names, values, quantity)?;
        for (i, value) in values.iter_mut().enumerate() {
            let (lower, upper) = bound(i, &self.limits[i]);
            if (lower..=upper).contains(value) {
                continue;
            }
            match policy {
                LimitPolicy::Clamp => *value = value.clamp(lower, upper),
                LimitPolicy::Reject => {
                    return Err(HalError::OutOfLimits {
                        joint: self.names[i].clone(),
                        quantity,
                        value: *value,
                        lower,
                        upper,
                    })
                }
            }
        }
        Ok(())
    }

    /// Fails when a reported effort exceeds the URDF effort limit.
    fn check_effort(&self, reading: &JointReading<N>) -> Result<(), HalError> {
        let Some(effort) = reading.effort_nm else {
            return Ok(());
        };
        for (i, &value) in effort.iter().enumerate() {
            let max = self.limits[i].effort;
            if value.abs() > max {
                return Err(HalError::OutOfLimits {
                    joint: self.names[i].clone(),
                    quantity: Quantity::Effort,
                    value,
                    lower: -max,
                    upper: max,
                });
            }
        }
        Ok(())
    }
}

/// A driver wrapped with wheel and/or arm limits; a side without limits passes through.
pub struct Limited<D> {
    inner: D,
    policy: LimitPolicy,
    /// Control period, for turning arm velocity limits into a per-command step bound.
    period: Duration,
    wheels: Option<JointLimitSet<WHEEL_JOINTS>>,
    arm: Option<JointLimitSet<ARM_JOINTS>>,
    last_arm_command_rad: Option<[f64; ARM_JOINTS]>,
}

impl<D> Limited<D> {
    pub fn new(inner: D, policy: LimitPolicy, period: Duration) -> Self {
        Limited {
            inner,
            policy,
            period,
            wheels: None,
            arm: None,
            last_arm_command_rad: None,
        }
    }

    pub fn with_wheel_limits(mut self, limits: JointLimitSet<WHEEL_JOINTS>) -> Self {
        self.wheels = Some(limits);
        self
    }

    pub fn with_arm_limits(mut self, limits: JointLimitSet<ARM_JOINTS>) -> Self {
        self.arm = Some(limits);
        self
    }

    pub fn inner(&self) -> &D {
        &self.inner
    }

    pub fn inner_mut(&mut self) -> &mut D {
        &mut self.inner
    }
}

impl<D: Drive> Drive for Limited<D> {
    fn enable(&mut self) -> Result<(), HalError> {
        // The arm holds its position on enable; the first command's step starts from there.
        self.last_arm_command_rad = None;
        self.inner.enable()
    }

    fn disable(&mut self) -> Result<(), HalError> {
        self.inner.disable()
    }

    fn fault(&self) -> Option<HalError> {
        self.inner.fault()
    }

    fn reset_fault(&mut self) -> Result<(), HalError> {
        self.inner.reset_fault()
    }

    fn sync(&mut self) -> Result<(), HalError> {
        self.inner.sync()
    }
}

impl<D: WheelDrive> WheelDrive for Limited<D> {
    fn command_velocity(&mut self, velocity_radps: &[f64; WHEEL_JOINTS]) -> Result<(), HalError> {
        let mut command = *velocity_radps;
        if let Some(limits) = &self.wheels {
            limits.apply(self.policy, Quantity::Velocity, &mut command, |_, l| {
                (-l.velocity, l.velocity)
            })?;
        }
        self.inner.command_velocity(&command)
    }

    fn read_wheels(&mut self) -> Result<JointReading<WHEEL_JOINTS>, HalError> {
        let reading = self.inner.read_wheels()?;
        if let Some(limits) = &self.wheels {
            limits.check_effort(&reading)?;
        }
        Ok(reading)
    }
}

impl<D: ArmDrive> ArmDrive for Limited<D> {
    fn command_position(&mut self, position_rad: &[f64; ARM_JOINTS]) -> Result<(), HalError> {
        let mut command = *position_rad;
        if let Some(limits) = &self.arm {
            let previous = match self.last_arm_command_rad {
                Some(previous) => previous,
                None => self.inner.read_arm()?.position_rad,
            };
            let period_s = self.period.as_secs_f64();
            limits.apply(self.policy, Quantity::Position, &mut command, |_, l| {
                (l.lower, l.upper)
            })?;
            // Bound the implied velocity (step / period), expressed as a velocity in errors.
            let mut velocity = std::array::from_fn(|i| (command[i] - previous[i]) / period_s);
            limits.apply(self.policy, Quantity::Velocity, &mut velocity, |_, l| {
                (-l.velocity, l.velocity)
            })?;
            command = std::array::from_fn(|i| previous[i] + velocity[i] * period_s);
        }
        self.inner.command_position(&command)?;
        self.last_arm_command_rad = Some(command);
        Ok(())
    }

    fn read_arm(&mut self) -> Result<JointReading<ARM_JOINTS>, HalError> {
        let reading = self.inner.read_arm()?;
        if let Some(limits) = &self.arm {
            limits.check_effort(&reading)?;
        }
        Ok(reading)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mock::{MockConfig, MockDrive, Response};

    const PERIOD: Duration = Duration::from_millis(20);

    fn unit() -> UnitSpec {
        UnitSpec::from_file(&moonhaul_core::config::repo_file("assets/unit.urdf")).unwrap()
    }

    fn arm_limits() -> JointLimitSet<ARM_JOINTS> {
        JointLimitSet::arm(&unit())
    }

    /// The shipped unit's arm as a mock, enabled, at the middle of every joint's range.
    fn arm(policy: LimitPolicy) -> Limited<MockDrive<ARM_JOINTS>> {
        let limits = arm_limits();
        let names = limits.names.clone();
        let config = MockConfig {
            response: Response::FirstOrder {
                time_constant_s: 0.001,
            },
            ..MockConfig::ideal(PERIOD)
        };
        let mut mock = MockDrive::new(names, config);
        let middle = limits.limits.map(|l| 0.5 * (l.lower + l.upper));
        mock.set_position(&middle);
        let mut arm = Limited::new(mock, policy, PERIOD).with_arm_limits(limits);
        arm.enable().unwrap();
        arm
    }

    #[test]
    fn limits_come_from_the_urdf() {
        let limits = arm_limits();
        // The values of assets/unit.urdf (after the KUKA iiwa 14).
        assert_eq!(limits.names[3], "arm_joint_4");
        assert!((limits.limits[3].upper - 2.0944).abs() < 1e-9);
        assert!((limits.limits[0].velocity - 1.48353).abs() < 1e-9);
        assert!((limits.limits[0].effort - 320.0).abs() < 1e-9);
        let wheels = JointLimitSet::wheels(&unit());
        assert_eq!(wheels.names, ["wheel_left_joint", "wheel_right_joint"]);
        assert_eq!(wheels.limits[0].upper, f64::INFINITY);
        assert!((wheels.limits[1].velocity - 10.0).abs() < 1e-9);
    }

    #[test]
    fn reject_names_the_joint_beyond_its_position_limit() {
        let mut arm = arm(LimitPolicy::Reject);
        let mut command = arm.read_arm().unwrap().position_rad;
        command[3] = 2.5; // joint 4 upper limit is 2.0944 rad
        let err = arm.command_position(&command).unwrap_err();
        match err {
            HalError::OutOfLimits {
                joint, quantity, ..
            } => {
                assert_eq!(joint, "arm_joint_4");
                assert_eq!(quantity, Quantity::Position);
            }
            other => panic!("unexpected {other:?}"),
        }
    }

    #[test]
    fn reject_names_the_joint_stepping_too_fast() {
        let mut arm = arm(LimitPolicy::Reject);
        let mut command = arm.read_arm().unwrap().position_rad;
        command[1] += 0.1; // 5 rad/s over 20 ms; joint 2 allows 1.48 rad/s
        let err = arm.command_position(&command).unwrap_err();
        assert!(matches!(
            err,
            HalError::OutOfLimits { ref joint, quantity: Quantity::Velocity, .. } if joint == "arm_joint_2"
        ));
    }

    #[test]
    fn clamp_keeps_commands_admissible() {
        let mut arm = arm(LimitPolicy::Clamp);
        let start = arm.read_arm().unwrap().position_rad;
        let limits = arm_limits();
        let target = [10.0; ARM_JOINTS];
        for _ in 0..200 {
            arm.command_position(&target).unwrap();
            arm.sync().unwrap();
        }
        let end = arm.read_arm().unwrap().position_rad;
        for i in 0..ARM_JOINTS {
            assert!(end[i] <= limits.limits[i].upper + 1e-9, "joint {i}");
            assert!(end[i] > start[i]);
        }
        // One clamped step moves at most velocity · period.
        let mut arm = self::arm(LimitPolicy::Clamp);
        arm.command_position(&target).unwrap();
        arm.sync().unwrap();
        let step = arm.read_arm().unwrap().position_rad[0] - start[0];
        assert!(step <= limits.limits[0].velocity * PERIOD.as_secs_f64() + 1e-6);
        assert!(arm.command_position(&[f64::NAN; ARM_JOINTS]).is_err());
    }

    #[test]
    fn wheel_velocity_is_clamped_and_effort_checked() {
        let names = ["wheel_left".to_owned(), "wheel_right".to_owned()];
        let limit = JointLimits {
            lower: f64::NEG_INFINITY,
            upper: f64::INFINITY,
            effort: 1.0,
            velocity: 2.0,
        };
        let set = JointLimitSet {
            names: names.clone(),
            limits: [limit; WHEEL_JOINTS],
        };
        let config = MockConfig {
            inertia_kgm2: Some(10.0),
            ..MockConfig::ideal(PERIOD)
        };
        let mock = MockDrive::new(names, config);
        let mut wheels =
            Limited::new(mock, LimitPolicy::Clamp, PERIOD).with_wheel_limits(set.clone());
        wheels.enable().unwrap();
        wheels.command_velocity(&[5.0, -5.0]).unwrap();
        wheels.sync().unwrap();
        // Ideal response: the wheel jumps to the clamped velocity, with a large inertial effort.
        let err = wheels.read_wheels().unwrap_err();
        assert!(matches!(
            err,
            HalError::OutOfLimits {
                quantity: Quantity::Effort,
                ..
            }
        ));
        wheels.sync().unwrap();
        let reading = wheels.read_wheels().unwrap();
        assert_eq!(reading.velocity_radps, [2.0, -2.0]);

        let mut strict = Limited::new(
            MockDrive::new(set.names.clone(), MockConfig::ideal(PERIOD)),
            LimitPolicy::Reject,
            PERIOD,
        )
        .with_wheel_limits(set);
        strict.enable().unwrap();
        let err = strict.command_velocity(&[0.0, -2.5]).unwrap_err();
        assert!(matches!(err, HalError::OutOfLimits { ref joint, .. } if joint == "wheel_right"));
    }
}
