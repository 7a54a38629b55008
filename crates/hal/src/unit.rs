//! The unit-level hardware interface, in the style of ros2_control's `SystemInterface`: the
//! onboard daemon reads a whole unit once and writes it once per control tick
//! ([`UnitHardware`]), and brings it up and down through a small lifecycle
//! (`activate` → active, `deactivate` → inactive).
//!
//! Backends:
//! - [`DriveUnit`]: any [`WheelDrive`] plus any [`ArmDrive`] (so [`crate::limits::Limited`]
//!   decorators compose), with an optional [`GraspModel`] for the gripper–payload force;
//! - [`MockUnit`]: two [`MockDrive`]s and a [`LoadShareGrasp`], with [`FaultInjection`];
//! - [`Cia402Master`]: the unit's nine CiA 402 drives on one CAN bus: a kernel interface
//!   ([`kernel_unit`], SocketCAN) or the [`VirtualBus`] with emulated drives
//!   ([`emulated_unit`]), which also takes [`FaultInjection`].
//!
//! Joint indices are the unit's order: wheels first (left, right), then the arm base to tip,
//! as [`moonhaul_core::unit::UnitSpec::joint_names`] lists them.
//!
//! Readings are passed through as measured: a backend never replaces a non-finite value, so the
//! daemon must check what it reads (see [`InjectedFault::SensorNan`]).

use std::time::Duration;

use moonhaul_core::state::{UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::UnitSpec;

use crate::can::protocol::Message;
use crate::can::{CanBus, Cia402Master, SocketCanBus, UnitCanConfig, VirtualBus};
use crate::mock::{MockConfig, MockDrive, MockFault};
use crate::{ArmDrive, Drive, HalError, JointReading, Quantity, WheelDrive};

/// Joints of one unit: wheels, then arm.
pub const UNIT_JOINTS: usize = WHEEL_JOINTS + ARM_JOINTS;

/// Everything one tick reads from a unit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnitReading {
    pub wheels: JointReading<WHEEL_JOINTS>,
    pub arm: JointReading<ARM_JOINTS>,
    /// Magnitude of the force between gripper and payload, N: a wrist F/T or current-based
    /// estimate; `None` when the backend has no such sensing.
    pub grasp_force_n: Option<f64>,
}

fn zero_reading<const N: usize>() -> JointReading<N> {
    JointReading {
        position_rad: [0.0; N],
        velocity_radps: [0.0; N],
        effort_nm: None,
        stamp: Duration::ZERO,
    }
}

impl Default for UnitReading {
    /// Zero positions and velocities, stamp 0, no effort, no grasp force.
    fn default() -> Self {
        UnitReading {
            wheels: zero_reading(),
            arm: zero_reading(),
            grasp_force_n: None,
        }
    }
}

/// Everything one tick writes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct UnitOutput {
    /// Wheel velocities, rad/s, and arm joint positions, rad.
    pub command: UnitCommand,
    /// Open the gripper (release the payload); `false` keeps it closed.
    pub grasp_open: bool,
}

/// One unit's hardware, read and written once per control tick (ros2_control's system
/// interface). Object-safe: the daemon holds a `Box<dyn UnitHardware>`.
pub trait UnitHardware: Send {
    /// inactive → active: enable every drive holding its current position.
    fn activate(&mut self) -> Result<(), HalError>;
    /// active → inactive: remove torque (after the daemon has issued a hold).
    fn deactivate(&mut self) -> Result<(), HalError>;
    /// The feedback of the latest cycle.
    fn read(&mut self, out: &mut UnitReading) -> Result<(), HalError>;
    /// Latches the commands and runs one control cycle (SYNC-driven backends), so the next
    /// read returns the new feedback.
    fn write(&mut self, out: &UnitOutput) -> Result<(), HalError>;
    /// The first latched fault, if any.
    fn fault(&self) -> Option<HalError>;
}

/// A fault a test injects into a unit; `joint` is in the unit's order (0..9, wheels first,
/// then the arm).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InjectedFault {
    /// The joint's drive faults (power stage off, fault latched).
    Motor { joint: usize },
    /// The joint's drive sends an emergency message.
    Emcy { joint: usize },
    /// The joint's drive goes silent: no heartbeat, no feedback.
    HeartbeatLoss { joint: usize },
    /// The joint's position sensor reads NaN from then on.
    SensorNan { joint: usize },
}

impl InjectedFault {
    /// The joint index the fault targets.
    pub fn joint(&self) -> usize {
        match *self {
            InjectedFault::Motor { joint }
            | InjectedFault::Emcy { joint }
            | InjectedFault::HeartbeatLoss { joint }
            | InjectedFault::SensorNan { joint } => joint,
        }
    }

    /// The kind, as errors name it.
    pub fn kind(&self) -> &'static str {
        match self {
            InjectedFault::Motor { .. } => "motor fault",
            InjectedFault::Emcy { .. } => "EMCY",
            InjectedFault::HeartbeatLoss { .. } => "heartbeat loss",
            InjectedFault::SensorNan { .. } => "sensor NaN",
        }
    }
}

impl std::fmt::Display for InjectedFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} on joint {}", self.kind(), self.joint())
    }
}

/// Fault injection into a unit backend, for tests and drills; kept off [`UnitHardware`] so a
/// real unit cannot be sabotaged through the daemon's handle.
pub trait FaultInjection {
    /// Injects `fault`; a kind the backend cannot produce, or a joint index outside 0..9, is an
    /// error naming the backend's bus and the fault.
    fn inject(&mut self, fault: InjectedFault) -> Result<(), HalError>;
}

fn injection_error(bus: &str, fault: InjectedFault, reason: &str) -> HalError {
    HalError::Bus {
        bus: bus.to_owned(),
        reason: format!("cannot inject {fault}: {reason}"),
    }
}

fn check_joint(bus: &str, fault: InjectedFault) -> Result<usize, HalError> {
    let joint = fault.joint();
    if joint < UNIT_JOINTS {
        Ok(joint)
    } else {
        Err(injection_error(
            bus,
            fault,
            &format!("the unit's joints are 0..{UNIT_JOINTS} (wheels, then arm)"),
        ))
    }
}

/// How the force between gripper and payload is obtained, advanced once per control cycle.
pub trait GraspModel: Send {
    /// Runs one control cycle in which the gripper was commanded open (`true`) or closed.
    fn cycle(&mut self, grasp_open: bool);
    /// The force magnitude after the latest cycle, N; `None` without grasp sensing.
    fn force_n(&self) -> Option<f64>;
}

/// No grasp sensing: [`UnitReading::grasp_force_n`] is always `None`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoGrasp;

impl GraspModel for NoGrasp {
    fn cycle(&mut self, _grasp_open: bool) {}

    fn force_n(&self) -> Option<f64> {
        None
    }
}

/// A rigid grasp carrying a fixed share of the payload's weight: the force is the load share
/// while the gripper is closed and 0 from the cycle in which it was commanded open on. Once
/// released it stays released (closing an empty gripper grasps nothing) until
/// [`LoadShareGrasp::regrasp`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadShareGrasp {
    load_share_n: f64,
    released: bool,
}

impl LoadShareGrasp {
    /// A closed grasp carrying `load_share_n`, N (finite, ≥ 0; see [`MockUnit::new`]).
    pub fn new(load_share_n: f64) -> Self {
        LoadShareGrasp {
            load_share_n,
            released: false,
        }
    }

    /// Whether the gripper has let go of the payload.
    pub fn released(&self) -> bool {
        self.released
    }

    /// Closes on the payload again, carrying the load share from the next read on.
    pub fn regrasp(&mut self) {
        self.released = false;
    }
}

impl GraspModel for LoadShareGrasp {
    fn cycle(&mut self, grasp_open: bool) {
        self.released |= grasp_open;
    }

    fn force_n(&self) -> Option<f64> {
        Some(if self.released {
            0.0
        } else {
            self.load_share_n
        })
    }
}

/// A unit made of a wheel drive and an arm drive (each possibly decorated, e.g. with
/// [`crate::limits::Limited`]) and a grasp model ([`NoGrasp`] unless one is given).
pub struct DriveUnit<W, A, G = NoGrasp> {
    wheels: W,
    arm: A,
    grasp: G,
}

impl<W, A> DriveUnit<W, A> {
    /// A unit without grasp sensing.
    pub fn new(wheels: W, arm: A) -> Self {
        DriveUnit {
            wheels,
            arm,
            grasp: NoGrasp,
        }
    }
}

impl<W, A, G> DriveUnit<W, A, G> {
    /// The same unit with `grasp` as its grasp-force model.
    pub fn with_grasp<H: GraspModel>(self, grasp: H) -> DriveUnit<W, A, H> {
        DriveUnit {
            wheels: self.wheels,
            arm: self.arm,
            grasp,
        }
    }

    pub fn wheels(&self) -> &W {
        &self.wheels
    }

    pub fn wheels_mut(&mut self) -> &mut W {
        &mut self.wheels
    }

    pub fn arm(&self) -> &A {
        &self.arm
    }

    pub fn arm_mut(&mut self) -> &mut A {
        &mut self.arm
    }

    pub fn grasp(&self) -> &G {
        &self.grasp
    }

    pub fn grasp_mut(&mut self) -> &mut G {
        &mut self.grasp
    }

    pub fn into_parts(self) -> (W, A, G) {
        (self.wheels, self.arm, self.grasp)
    }
}

impl<W: WheelDrive, A: ArmDrive, G> DriveUnit<W, A, G> {
    /// Syncs both drives, even when the first fails, and returns the first error.
    fn sync_both(&mut self) -> Result<(), HalError> {
        let wheels = self.wheels.sync();
        let arm = self.arm.sync();
        wheels.and(arm)
    }
}

impl<W, A, G> UnitHardware for DriveUnit<W, A, G>
where
    W: WheelDrive + Send,
    A: ArmDrive + Send,
    G: GraspModel,
{
    /// Enables the wheels, then the arm, then runs one cycle so feedback exists.
    fn activate(&mut self) -> Result<(), HalError> {
        self.wheels.enable()?;
        self.arm.enable()?;
        self.sync_both()
    }

    /// Disables both drives (both are tried, even when the first fails).
    fn deactivate(&mut self) -> Result<(), HalError> {
        let wheels = self.wheels.disable();
        let arm = self.arm.disable();
        wheels.and(arm)
    }

    fn read(&mut self, out: &mut UnitReading) -> Result<(), HalError> {
        out.wheels = self.wheels.read_wheels()?;
        out.arm = self.arm.read_arm()?;
        out.grasp_force_n = self.grasp.force_n();
        Ok(())
    }

    /// Latches both commands and runs one cycle of both drives. A rejected command (not
    /// enabled, non-finite, out of limits, faulted) leaves the previous target latched, but the
    /// cycle still runs so feedback and supervision stay current; the first error is returned.
    fn write(&mut self, out: &UnitOutput) -> Result<(), HalError> {
        let wheels = self
            .wheels
            .command_velocity(&out.command.wheel_velocity_radps);
        let arm = self.arm.command_position(&out.command.arm_position_rad);
        let synced = self.sync_both();
        self.grasp.cycle(out.grasp_open);
        wheels.and(arm).and(synced)
    }

    fn fault(&self) -> Option<HalError> {
        self.wheels.fault().or_else(|| self.arm.fault())
    }
}

/// The bus name mock errors carry.
const MOCK_BUS: &str = "mock";

/// The mock unit (ros2_control `mock_components` style): a [`DriveUnit`] of two
/// [`MockDrive`]s with a [`LoadShareGrasp`], plus [`FaultInjection`]. Time moves only in
/// `write` (one period), so a run is deterministic and takes no wall time.
pub struct MockUnit {
    unit: DriveUnit<MockDrive<WHEEL_JOINTS>, MockDrive<ARM_JOINTS>, LoadShareGrasp>,
    /// Joints whose reported position is NaN (injected), unit order.
    nan_position: [bool; UNIT_JOINTS],
}

impl MockUnit {
    /// A mock of the unit `spec` (joint names and order), at rest with the arm at
    /// `initial_arm_rad` and the gripper closed carrying `load_share_n`, N. `period` is the
    /// control period one `write` advances (it replaces `config.period`). Fails on a
    /// non-finite arm position (naming the joint) or a load share that is not a finite
    /// force ≥ 0.
    pub fn new(
        period: Duration,
        config: MockConfig,
        spec: &UnitSpec,
        initial_arm_rad: &[f64; ARM_JOINTS],
        load_share_n: f64,
    ) -> Result<Self, HalError> {
        crate::check_finite(&spec.arm_joints, initial_arm_rad, Quantity::Position)?;
        if !(load_share_n.is_finite() && load_share_n >= 0.0) {
            return Err(HalError::Bus {
                bus: MOCK_BUS.to_owned(),
                reason: format!("grasp load share {load_share_n} N is not a finite force ≥ 0"),
            });
        }
        let config = MockConfig { period, ..config };
        let wheels = MockDrive::new(spec.wheel_joints.clone(), config.clone());
        let mut arm = MockDrive::new(spec.arm_joints.clone(), config);
        arm.set_position(initial_arm_rad);
        Ok(MockUnit {
            unit: DriveUnit::new(wheels, arm).with_grasp(LoadShareGrasp::new(load_share_n)),
            nan_position: [false; UNIT_JOINTS],
        })
    }

    /// The underlying drives and grasp, e.g. to inject [`MockFault`]s that have no
    /// [`InjectedFault`] (stuck joint, latency spike, lost bus).
    pub fn drives(
        &self,
    ) -> &DriveUnit<MockDrive<WHEEL_JOINTS>, MockDrive<ARM_JOINTS>, LoadShareGrasp> {
        &self.unit
    }

    pub fn drives_mut(
        &mut self,
    ) -> &mut DriveUnit<MockDrive<WHEEL_JOINTS>, MockDrive<ARM_JOINTS>, LoadShareGrasp> {
        &mut self.unit
    }

    /// Simulated time since creation.
    pub fn now(&self) -> Duration {
        self.unit.wheels().now()
    }

    /// Clears NaN sensors and what [`MockDrive::heal`] clears; a latched drive fault still
    /// needs a reset, as on real hardware.
    pub fn heal(&mut self) {
        self.nan_position = [false; UNIT_JOINTS];
        self.unit.wheels_mut().heal();
        self.unit.arm_mut().heal();
    }
}

impl UnitHardware for MockUnit {
    fn activate(&mut self) -> Result<(), HalError> {
        self.unit.activate()
    }

    fn deactivate(&mut self) -> Result<(), HalError> {
        self.unit.deactivate()
    }

    fn read(&mut self, out: &mut UnitReading) -> Result<(), HalError> {
        self.unit.read(out)?;
        let (wheels, arm) = self.nan_position.split_at(WHEEL_JOINTS);
        for (q, _) in out
            .wheels
            .position_rad
            .iter_mut()
            .zip(wheels)
            .filter(|x| *x.1)
        {
            *q = f64::NAN;
        }
        for (q, _) in out.arm.position_rad.iter_mut().zip(arm).filter(|x| *x.1) {
            *q = f64::NAN;
        }
        Ok(())
    }

    fn write(&mut self, out: &UnitOutput) -> Result<(), HalError> {
        self.unit.write(out)
    }

    fn fault(&self) -> Option<HalError> {
        self.unit.fault()
    }
}

impl FaultInjection for MockUnit {
    /// Motor and EMCY latch a [`MockFault::DriveFault`] (the mock has no emergency messages:
    /// an EMCY latches a fault, as the CiA 402 master does); heartbeat loss is a
    /// [`MockFault::EncoderDropout`] (reads fail with [`HalError::NoFeedback`]); a NaN sensor
    /// makes the joint's reported position NaN from the next read on.
    fn inject(&mut self, fault: InjectedFault) -> Result<(), HalError> {
        let joint = check_joint(MOCK_BUS, fault)?;
        let mock = match fault {
            InjectedFault::Motor { .. } => MockFault::DriveFault {
                joint: 0,
                reason: "motor fault (injected)".to_owned(),
            },
            InjectedFault::Emcy { .. } => MockFault::DriveFault {
                joint: 0,
                reason: "emergency message (injected EMCY)".to_owned(),
            },
            InjectedFault::HeartbeatLoss { .. } => MockFault::EncoderDropout { joint: 0 },
            InjectedFault::SensorNan { .. } => {
                self.nan_position[joint] = true;
                return Ok(());
            }
        };
        // Re-aim the fault at the joint's index within its drive.
        let retarget = |mock: MockFault, j: usize| match mock {
            MockFault::DriveFault { reason, .. } => MockFault::DriveFault { joint: j, reason },
            MockFault::EncoderDropout { .. } => MockFault::EncoderDropout { joint: j },
            other => other,
        };
        if joint < WHEEL_JOINTS {
            self.unit.wheels_mut().inject(retarget(mock, joint));
        } else {
            self.unit
                .arm_mut()
                .inject(retarget(mock, joint - WHEEL_JOINTS));
        }
        Ok(())
    }
}

impl<B: CanBus + Send> UnitHardware for Cia402Master<B> {
    /// Enables every drive (running start-up first if needed), then one cycle.
    fn activate(&mut self) -> Result<(), HalError> {
        self.enable_drives()?;
        Drive::sync(self)
    }

    fn deactivate(&mut self) -> Result<(), HalError> {
        Drive::disable(self)
    }

    /// Positions, velocities and (where the config rates the drives' torque) efforts of the
    /// last cycle. `grasp_force_n` is always `None`: the CiA 402 drives have no force sensing,
    /// and a gripper force estimate needs a model of the gripper this bus does not carry.
    fn read(&mut self, out: &mut UnitReading) -> Result<(), HalError> {
        out.wheels = self.read_wheels()?;
        out.arm = self.read_arm()?;
        out.grasp_force_n = None;
        Ok(())
    }

    /// Latches both commands and runs one cycle (RPDOs, SYNC, feedback). As for
    /// [`DriveUnit`], the cycle runs even when a command is rejected, so heartbeats and
    /// feedback stay supervised; the first error is returned. `grasp_open` is not a drive of
    /// this bus and is ignored here.
    fn write(&mut self, out: &UnitOutput) -> Result<(), HalError> {
        let wheels = self.command_velocity(&out.command.wheel_velocity_radps);
        let arm = self.command_position(&out.command.arm_position_rad);
        let synced = Drive::sync(self);
        wheels.and(arm).and(synced)
    }

    fn fault(&self) -> Option<HalError> {
        Drive::fault(self)
    }
}

/// Emergency code of an injected motor fault: continuous over-current.
pub const INJECTED_MOTOR_FAULT_CODE: u16 = 0x2310;
/// Emergency code of an injected EMCY (without a drive fault): excess drive temperature.
pub const INJECTED_EMCY_CODE: u16 = 0x4310;
/// EMCY error register of an injected EMCY: generic error.
const INJECTED_EMCY_REGISTER: u8 = 0x01;

impl FaultInjection for Cia402Master<VirtualBus> {
    /// Acts on the joint's emulated drive: a motor fault puts it in Fault (statusword and an
    /// EMCY); an EMCY is an emergency frame from it without a state change; heartbeat loss
    /// makes it silent (the master then reports the missing process data or heartbeat,
    /// whichever watchdog expires first). A NaN sensor cannot happen on CAN (positions are
    /// integer counts) and is refused.
    fn inject(&mut self, fault: InjectedFault) -> Result<(), HalError> {
        let joint = check_joint(self.bus().name(), fault)?;
        let Some(node) = self.drive_states().nth(joint).map(|(at, _)| at.node) else {
            return Err(injection_error(
                self.bus().name(),
                fault,
                "the unit config has no such drive",
            ));
        };
        if let InjectedFault::SensorNan { .. } = fault {
            return Err(injection_error(
                self.bus().name(),
                fault,
                "CiA 402 positions are integer counts and cannot be NaN",
            ));
        }
        if let InjectedFault::Emcy { .. } = fault {
            self.bus_mut().inject(
                Message::Emergency {
                    node,
                    code: INJECTED_EMCY_CODE,
                    register: INJECTED_EMCY_REGISTER,
                }
                .encode(),
            );
            return Ok(());
        }
        let bus = self.bus_mut();
        let Some(drive) = bus.drive_mut(node) else {
            return Err(injection_error(
                bus.name(),
                fault,
                &format!("no emulated drive with CAN node {node} on the bus"),
            ));
        };
        match fault {
            InjectedFault::Motor { .. } => drive.raise_fault(INJECTED_MOTOR_FAULT_CODE),
            _ => drive.faults.silent = true,
        }
        Ok(())
    }
}

impl FaultInjection for Cia402Master<SocketCanBus> {
    /// Refuses: a drill never breaks real drives on purpose (`--hal can-emulated` injects into
    /// emulated ones).
    fn inject(&mut self, fault: InjectedFault) -> Result<(), HalError> {
        check_joint(self.bus().name(), fault)?;
        Err(injection_error(
            self.bus().name(),
            fault,
            "faults are injected into emulated drives only, not into real ones",
        ))
    }
}

/// The unit's nine drives on the kernel CAN interface `interface` (SocketCAN, e.g. `can0`)
/// behind a CiA 402 master that has run start-up; `activate` enables them. Fails naming the
/// interface when it cannot be opened (no AF_CAN in the kernel, no such interface) and naming
/// the drive when one does not answer start-up.
pub fn kernel_unit(
    config: &UnitCanConfig,
    interface: &str,
) -> Result<Cia402Master<SocketCanBus>, HalError> {
    let bus = SocketCanBus::open(interface).map_err(crate::can::CanError::from)?;
    let mut master = Cia402Master::new(bus, config);
    master.start_up()?;
    Ok(master)
}

/// The unit's nine drives emulated on a [`VirtualBus`] behind a CiA 402 master that has run
/// start-up (SDO configuration, NMT start); `activate` enables them. Lets the daemon run its
/// CAN backend without kernel CAN.
pub fn emulated_unit(config: &UnitCanConfig) -> Result<Cia402Master<VirtualBus>, HalError> {
    emulated_unit_on(config, |bus| bus)
}

/// As [`emulated_unit`], with the virtual bus wrapped by `wrap` first (e.g. in a
/// [`crate::can::RecordingBus`] to log all traffic, start-up included).
pub fn emulated_unit_on<B: CanBus>(
    config: &UnitCanConfig,
    wrap: impl FnOnce(VirtualBus) -> B,
) -> Result<Cia402Master<B>, HalError> {
    let mut master = Cia402Master::new(wrap(VirtualBus::for_unit(config)), config);
    master.start_up()?;
    Ok(master)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::can::config::tests::unit_config;
    use crate::can::CanError;
    use crate::limits::{JointLimitSet, LimitPolicy, Limited};

    const PERIOD: Duration = Duration::from_millis(20);

    fn spec() -> UnitSpec {
        UnitSpec::from_file(&moonhaul_core::config::repo_file("assets/unit.urdf")).unwrap()
    }

    fn arm_start() -> [f64; ARM_JOINTS] {
        std::array::from_fn(|j| 0.05 * j as f64)
    }

    fn mock(load_share_n: f64) -> MockUnit {
        let mut unit = MockUnit::new(
            PERIOD,
            MockConfig::ideal(Duration::from_secs(1)),
            &spec(),
            &arm_start(),
            load_share_n,
        )
        .unwrap();
        unit.activate().unwrap();
        unit
    }

    fn output(wheels: [f64; WHEEL_JOINTS], arm: [f64; ARM_JOINTS]) -> UnitOutput {
        UnitOutput {
            command: UnitCommand {
                wheel_velocity_radps: wheels,
                arm_position_rad: arm,
            },
            grasp_open: false,
        }
    }

    fn names_joint(err: &HalError, joint: &str) -> bool {
        err.to_string().contains(joint)
    }

    #[test]
    fn default_reading_is_zero() {
        let r = UnitReading::default();
        assert_eq!(r.arm.position_rad, [0.0; ARM_JOINTS]);
        assert_eq!(r.wheels.stamp, Duration::ZERO);
        assert_eq!((r.arm.effort_nm, r.grasp_force_n), (None, None));
        assert_eq!(UnitOutput::default().command, UnitCommand::default());
    }

    #[test]
    fn mock_unit_mirrors_commands_through_read_and_write() {
        let mut unit = mock(20.0);
        let mut reading = UnitReading::default();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.arm.position_rad, arm_start());
        assert_eq!(reading.wheels.stamp, PERIOD, "activate ran one cycle");

        let arm: [f64; ARM_JOINTS] = std::array::from_fn(|j| 0.1 - 0.02 * j as f64);
        unit.write(&output([1.0, -0.5], arm)).unwrap();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.arm.position_rad, arm);
        assert_eq!(reading.wheels.velocity_radps, [1.0, -0.5]);
        assert!((reading.wheels.position_rad[0] - 0.02).abs() < 1e-12);
        assert_eq!(reading.arm.stamp, 2 * PERIOD);
        assert_eq!(reading.grasp_force_n, Some(20.0));
        assert_eq!(unit.fault(), None);

        // A non-finite command is refused by joint; the cycle still runs on the old targets.
        let mut bad = arm;
        bad[3] = f64::NAN;
        let err = unit.write(&output([1.0, -0.5], bad)).unwrap_err();
        assert!(names_joint(&err, &spec().arm_joints[3]), "{err}");
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.arm.position_rad, arm);
        assert_eq!(reading.arm.stamp, 3 * PERIOD);

        unit.deactivate().unwrap();
        assert!(matches!(
            unit.write(&output([0.0; 2], arm)),
            Err(HalError::NotEnabled { .. })
        ));
    }

    #[test]
    fn mock_unit_rejects_bad_construction() {
        let mut arm = arm_start();
        arm[6] = f64::INFINITY;
        let config = MockConfig::ideal(PERIOD);
        let err = MockUnit::new(PERIOD, config.clone(), &spec(), &arm, 1.0).err();
        assert!(matches!(err, Some(HalError::NonFinite { ref joint, .. })
            if *joint == spec().arm_joints[6]));
        for load in [f64::NAN, -1.0] {
            let err = MockUnit::new(PERIOD, config.clone(), &spec(), &arm_start(), load).err();
            assert!(matches!(err, Some(HalError::Bus { .. })), "{err:?}");
        }
    }

    #[test]
    fn grasp_force_drops_to_zero_after_grasp_open() {
        let mut unit = mock(24.5);
        let mut reading = UnitReading::default();
        let mut out = output([0.0; 2], arm_start());
        unit.write(&out).unwrap();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, Some(24.5));
        out.grasp_open = true;
        unit.write(&out).unwrap();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, Some(0.0));
        // Closing an empty gripper grasps nothing.
        out.grasp_open = false;
        unit.write(&out).unwrap();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, Some(0.0));
        unit.drives_mut().grasp_mut().regrasp();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, Some(24.5));
    }

    #[test]
    fn mock_injected_faults_name_the_joint() {
        let names: Vec<String> = spec().joint_names().map(str::to_owned).collect();
        let out = output([0.5; 2], arm_start());
        let mut reading = UnitReading::default();

        for (joint, fault) in [
            (1, InjectedFault::Motor { joint: 1 }),
            (5, InjectedFault::Motor { joint: 5 }),
            (8, InjectedFault::Emcy { joint: 8 }),
        ] {
            let mut unit = mock(1.0);
            unit.inject(fault).unwrap();
            let err = unit.write(&out).unwrap_err();
            assert!(names_joint(&err, &names[joint]), "{fault}: {err}");
            let latched = unit.fault().unwrap();
            assert!(names_joint(&latched, &names[joint]), "{fault}: {latched}");
        }

        let mut unit = mock(1.0);
        unit.inject(InjectedFault::HeartbeatLoss { joint: 3 })
            .unwrap();
        unit.write(&out).unwrap();
        let err = unit.read(&mut reading).unwrap_err();
        assert!(
            matches!(err, HalError::NoFeedback { ref joint, .. } if *joint == names[3]),
            "{err}"
        );

        let mut unit = mock(1.0);
        unit.inject(InjectedFault::SensorNan { joint: 0 }).unwrap();
        unit.inject(InjectedFault::SensorNan { joint: 6 }).unwrap();
        for _ in 0..3 {
            unit.write(&out).unwrap();
            unit.read(&mut reading).unwrap();
            assert!(reading.wheels.position_rad[0].is_nan());
            assert!(reading.wheels.position_rad[1].is_finite());
            assert!(reading.arm.position_rad[4].is_nan());
            assert_eq!(
                reading
                    .arm
                    .position_rad
                    .iter()
                    .filter(|q| q.is_nan())
                    .count(),
                1
            );
        }
        unit.heal();
        unit.read(&mut reading).unwrap();
        assert!(reading.wheels.position_rad[0].is_finite());

        let err = unit.inject(InjectedFault::Motor { joint: 9 }).unwrap_err();
        assert!(err.to_string().contains("motor fault on joint 9"), "{err}");
    }

    #[test]
    fn limited_drives_compose_into_a_unit() {
        let spec = spec();
        let config = MockConfig::ideal(PERIOD);
        let wheels = Limited::new(
            MockDrive::new(spec.wheel_joints.clone(), config.clone()),
            LimitPolicy::Reject,
            PERIOD,
        )
        .with_wheel_limits(JointLimitSet::wheels(&spec));
        let arm = Limited::new(
            MockDrive::new(spec.arm_joints.clone(), config),
            LimitPolicy::Reject,
            PERIOD,
        )
        .with_arm_limits(JointLimitSet::arm(&spec));
        let mut unit: Box<dyn UnitHardware> = Box::new(DriveUnit::new(wheels, arm));
        unit.activate().unwrap();
        let mut reading = UnitReading::default();
        unit.write(&output([0.1, 0.1], [0.0; ARM_JOINTS])).unwrap();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, None);
        assert_eq!(reading.wheels.velocity_radps, [0.1, 0.1]);
        let err = unit
            .write(&output([1e6, 0.1], [0.0; ARM_JOINTS]))
            .unwrap_err();
        assert!(
            matches!(err, HalError::OutOfLimits { ref joint, .. } if *joint == spec.wheel_joints[0]),
            "{err}"
        );
    }

    #[test]
    fn can_master_on_emulated_bus_follows_commands_as_a_trait_object() {
        let config = unit_config();
        let mut unit: Box<dyn UnitHardware> = Box::new(emulated_unit(&config).unwrap());
        unit.activate().unwrap();
        let mut reading = UnitReading::default();
        unit.read(&mut reading).unwrap();
        assert_eq!(reading.grasp_force_n, None);
        let start = reading.arm.position_rad;
        let target: [f64; ARM_JOINTS] = std::array::from_fn(|j| start[j] + 0.1);
        let out = output([2.0, -1.0], target);
        let stamp = reading.arm.stamp;
        for _ in 0..25 {
            unit.write(&out).unwrap();
        }
        unit.read(&mut reading).unwrap();
        assert!(reading.arm.stamp > stamp);
        let wheels = reading.wheels.velocity_radps.iter();
        for (v, v_cmd) in wheels.zip(&out.command.wheel_velocity_radps) {
            assert!((v - v_cmd).abs() < 0.05, "{v} vs {v_cmd}");
        }
        for (j, (q, q_cmd)) in reading.arm.position_rad.iter().zip(&target).enumerate() {
            assert!((q - q_cmd).abs() < 5e-3, "arm {j}: {q} vs {q_cmd}");
        }
        assert!(reading.wheels.position_rad[0] > 0.5 && reading.wheels.position_rad[1] < 0.0);
        assert_eq!(unit.fault(), None);
        unit.deactivate().unwrap();
    }

    /// Writes until the master reports a fault, within `cycles`.
    fn fault_within(unit: &mut dyn UnitHardware, out: &UnitOutput, cycles: usize) -> HalError {
        for _ in 0..cycles {
            if let Err(err) = unit.write(out) {
                return err;
            }
        }
        panic!("no fault within {cycles} cycles");
    }

    #[test]
    fn can_master_reports_injected_faults_by_joint() {
        let config = unit_config();
        let names: Vec<String> = config.drives().map(|d| d.joint.clone()).collect();
        let hold = |m: &mut Cia402Master<VirtualBus>| {
            let mut r = UnitReading::default();
            m.read(&mut r).unwrap();
            output([0.0; 2], r.arm.position_rad)
        };
        for fault in [
            InjectedFault::Motor { joint: 4 },
            InjectedFault::Emcy { joint: 0 },
            InjectedFault::HeartbeatLoss { joint: 7 },
        ] {
            let mut master = emulated_unit(&config).unwrap();
            master.activate().unwrap();
            let out = hold(&mut master);
            master.inject(fault).unwrap();
            let err = fault_within(&mut master, &out, 50);
            let joint = &names[fault.joint()];
            assert!(names_joint(&err, joint), "{fault}: {err}");
            let expected = match (fault, &err) {
                (InjectedFault::Motor { .. }, HalError::Can(CanError::Emergency { code, .. })) => {
                    *code == INJECTED_MOTOR_FAULT_CODE
                }
                (InjectedFault::Motor { .. }, HalError::Can(CanError::DriveFault { .. })) => true,
                (InjectedFault::Emcy { .. }, HalError::Can(CanError::Emergency { code, .. })) => {
                    *code == INJECTED_EMCY_CODE
                }
                (
                    InjectedFault::HeartbeatLoss { .. },
                    HalError::Can(CanError::HeartbeatLost { .. } | CanError::NoFeedback { .. }),
                ) => true,
                _ => false,
            };
            assert!(expected, "{fault}: {err:?}");
            let unit: &dyn UnitHardware = &master;
            assert_eq!(unit.fault(), Some(err));
        }

        let mut master = emulated_unit(&config).unwrap();
        let err = master
            .inject(InjectedFault::SensorNan { joint: 2 })
            .unwrap_err();
        assert!(
            err.to_string().contains("sensor NaN") && err.to_string().contains("can0"),
            "{err}"
        );
        let err = master
            .inject(InjectedFault::HeartbeatLoss { joint: 42 })
            .unwrap_err();
        assert!(err.to_string().contains("joint 42"), "{err}");
    }
}
