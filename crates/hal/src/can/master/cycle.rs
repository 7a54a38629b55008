//! The cyclic exchange: each cycle sends the RPDOs (controlword + target) and a SYNC, then
//! handles everything received until the period ends (TPDO feedback, heartbeats, EMCYs) and
//! runs the heartbeat and process-data watchdogs.

use std::time::Duration;

use super::Cia402Master;
use crate::can::cia402::{self as od, next_controlword, Cia402State, TPDO1, TPDO2};
use crate::can::protocol::{
    emergency_description, pack_pdo, unpack_pdo, DecodeError, Message, NmtState, TPDO_BASE,
};
use crate::can::{CanBus, CanError, CanFrame};

impl<B: CanBus> Cia402Master<B> {
    /// One control cycle: RPDOs, SYNC, then everything received until the period ends.
    pub fn cycle(&mut self) -> Result<(), CanError> {
        let start = self.bus.now();
        if self.started.is_some() {
            let faulted = self.first_fault().is_some();
            for i in 0..self.axes.len() {
                let axis = &self.axes[i];
                let holding = axis.state == Some(Cia402State::OperationEnabled);
                let enable = self.enable && (!faulted || holding);
                let cw = next_controlword(axis.state, enable, self.reset, axis.controlword);
                let target = if self.enable && axis.reached_enabled {
                    axis.target
                } else {
                    axis.hold_target()
                };
                let (data, len) = pack_pdo(axis.config.mode.rpdo(), |e| {
                    if e.index == od::CONTROLWORD {
                        cw.into()
                    } else {
                        target as u32
                    }
                });
                self.axes[i].controlword = cw;
                let node = self.axes[i].at.node;
                self.send(Message::Rpdo {
                    node,
                    pdo: 1,
                    data: &data[..len],
                })?;
            }
        }
        self.send(Message::Sync)?;
        let deadline = start + self.config.sync_period();
        while let Some(frame) = self.recv(deadline)? {
            self.handle(&frame);
        }
        self.supervise();
        self.stats.cycles += 1;
        Ok(())
    }

    /// Applies one received frame; anything wrong latches a fault, nothing panics.
    pub fn handle(&mut self, frame: &CanFrame) {
        let now = self.bus.now();
        let cob_id = frame.id();
        let axis = self.node_axis[usize::from(cob_id & 0x7F)].map(usize::from);
        let message = match Message::decode(frame) {
            Ok(message) => message,
            Err(reason) => {
                match axis {
                    Some(i) => {
                        let at = self.axes[i].at.clone();
                        self.axes[i].latch(CanError::Malformed { at, cob_id, reason })
                    }
                    None => self.foreign(cob_id, format!("undecodable: {reason}")),
                }
                return;
            }
        };
        let i = match (message, axis) {
            (
                Message::Nmt { .. }
                | Message::Sync
                | Message::Rpdo { .. }
                | Message::SdoRequest { .. },
                _,
            ) => {
                return self.foreign(cob_id, "a frame only a master sends".into());
            }
            (_, None) => return self.foreign(cob_id, "unknown node".into()),
            (_, Some(i)) => i,
        };
        let started = self.started.is_some();
        let axis = &mut self.axes[i];
        match message {
            Message::Heartbeat { state, .. } => {
                axis.last_heartbeat = now;
                if state == NmtState::BootUp && started {
                    axis.latch(CanError::Rebooted {
                        at: axis.at.clone(),
                    });
                }
            }
            Message::Emergency { code, register, .. } if code != 0 => {
                axis.latch(CanError::Emergency {
                    at: axis.at.clone(),
                    code,
                    register,
                    description: emergency_description(code),
                })
            }
            Message::Tpdo { pdo: 1, data, .. } => self.tpdo1(i, data, now),
            Message::Tpdo { pdo: 2, data, .. } => {
                let (mut velocity, mut torque) = (0, 0);
                let unpacked = unpack_pdo(&TPDO2, data, |e, v| match e.index {
                    od::VELOCITY_ACTUAL => velocity = v as i32,
                    _ => torque = v as u16 as i16,
                });
                match unpacked {
                    Ok(()) => (axis.velocity_countsps, axis.torque_permille) = (velocity, torque),
                    Err(reason) => axis.latch(CanError::Malformed {
                        at: axis.at.clone(),
                        cob_id,
                        reason,
                    }),
                }
            }
            Message::Tpdo { .. } => axis.latch(CanError::Malformed {
                at: axis.at.clone(),
                cob_id,
                reason: DecodeError::Unsupported,
            }),
            // Error resets and SDO replies that arrive after their time-out carry no news.
            _ => {}
        }
    }

    fn tpdo1(&mut self, i: usize, data: &[u8], now: Duration) {
        let enable = self.enable;
        let axis = &mut self.axes[i];
        let (mut statusword, mut position) = (0, 0);
        let unpacked = unpack_pdo(&TPDO1, data, |e, v| match e.index {
            od::STATUSWORD => statusword = v as u16,
            _ => position = v as i32,
        });
        if let Err(reason) = unpacked {
            return axis.latch(CanError::Malformed {
                at: axis.at.clone(),
                cob_id: TPDO_BASE[0] + u16::from(axis.at.node),
                reason,
            });
        }
        axis.position_counts = match axis.raw_position {
            Some(last) => axis.position_counts + i64::from(position.wrapping_sub(last)),
            None => position.into(),
        };
        axis.raw_position = Some(position);
        axis.feedback_stamp = Some(now);
        let state = Cia402State::from_statusword(statusword);
        match state {
            Some(Cia402State::Fault | Cia402State::FaultReactionActive) => {
                axis.latch(CanError::DriveFault {
                    at: axis.at.clone(),
                    statusword,
                })
            }
            Some(Cia402State::OperationEnabled) if enable && !axis.reached_enabled => {
                // Commands start from where the drive was enabled: no jump.
                axis.reached_enabled = true;
                axis.target = axis.hold_target();
            }
            Some(Cia402State::OperationEnabled) => {}
            Some(other) if enable && axis.reached_enabled => {
                axis.reached_enabled = false;
                axis.latch(CanError::LeftOperationEnabled {
                    at: axis.at.clone(),
                    state: other,
                });
            }
            _ => {}
        }
        axis.state = state;
    }

    fn foreign(&mut self, cob_id: u16, what: String) {
        self.bus_fault
            .get_or_insert(CanError::Foreign { cob_id, what });
    }

    /// Heartbeat and process-data time-outs.
    fn supervise(&mut self) {
        let Some(started) = self.started else {
            return;
        };
        let now = self.bus.now();
        let heartbeat_timeout = Duration::from_secs_f64(self.config.heartbeat_timeout_s);
        let feedback_timeout = Duration::from_secs_f64(self.config.feedback_timeout_s);
        for axis in &mut self.axes {
            let silent = now.saturating_sub(axis.last_heartbeat.max(started));
            if silent > heartbeat_timeout {
                axis.latch(CanError::HeartbeatLost {
                    at: axis.at.clone(),
                    waited: silent,
                });
            }
            let stale = now.saturating_sub(axis.feedback_stamp.unwrap_or(started).max(started));
            if stale > feedback_timeout {
                axis.latch(CanError::NoFeedback {
                    at: axis.at.clone(),
                    waited: stale,
                });
            }
        }
    }
}
