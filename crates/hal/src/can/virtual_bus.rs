//! An in-memory CAN bus with emulated drives and a simulated clock. A frame the master sends
//! reaches every drive at once; what drives send queues for the master. The clock advances in
//! fixed steps only while the master waits in [`CanBus::recv_until`], stepping the drives'
//! motors and heartbeats, so runs are deterministic and take no wall time.

use std::collections::VecDeque;
use std::time::Duration;

use super::config::UnitCanConfig;
use super::{BusError, CanBus, CanFrame, EmulatedDrive};

pub struct VirtualBus {
    name: String,
    now: Duration,
    step: Duration,
    drives: Vec<EmulatedDrive>,
    /// Frames for the master, in arrival order.
    inbox: VecDeque<CanFrame>,
}

impl VirtualBus {
    /// An empty bus named `name` whose clock advances by `step`.
    pub fn new(name: &str, step: Duration) -> Self {
        VirtualBus {
            name: name.to_owned(),
            now: Duration::ZERO,
            step: step.max(Duration::from_micros(1)),
            drives: Vec::new(),
            inbox: VecDeque::new(),
        }
    }

    /// The unit's nine drives, freshly powered up, on a bus named after its interface.
    pub fn for_unit(config: &UnitCanConfig) -> Self {
        let mut bus = VirtualBus::new(
            &config.interface,
            Duration::from_secs_f64(config.emulator.step_s),
        );
        for drive in config.drives() {
            bus.attach(EmulatedDrive::new(drive, config.emulator));
        }
        bus
    }

    pub fn attach(&mut self, mut drive: EmulatedDrive) {
        drive.advance(self.now);
        drive.drain(&mut self.inbox);
        self.drives.push(drive);
    }

    pub fn drive(&self, node: u8) -> Option<&EmulatedDrive> {
        self.drives.iter().find(|d| d.node() == node)
    }

    /// For fault injection.
    pub fn drive_mut(&mut self, node: u8) -> Option<&mut EmulatedDrive> {
        self.drives.iter_mut().find(|d| d.node() == node)
    }

    /// Puts a frame on the bus as if another device sent it (malformed frames, strangers).
    pub fn inject(&mut self, frame: CanFrame) {
        self.inbox.push_back(frame);
    }
}

impl CanBus for VirtualBus {
    fn name(&self) -> &str {
        &self.name
    }

    fn now(&self) -> Duration {
        self.now
    }

    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        for drive in &mut self.drives {
            drive.receive(frame);
            drive.drain(&mut self.inbox);
        }
        Ok(())
    }

    fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError> {
        loop {
            if let Some(frame) = self.inbox.pop_front() {
                return Ok(Some(frame));
            }
            if self.now >= deadline {
                return Ok(None);
            }
            self.now = (self.now + self.step).min(deadline);
            for drive in &mut self.drives {
                drive.advance(self.now);
                drive.drain(&mut self.inbox);
            }
        }
    }
}
