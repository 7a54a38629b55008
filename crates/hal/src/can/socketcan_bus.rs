//! A real CAN bus through Linux SocketCAN (the `socketcan` crate), blocking with a receive
//! time-out: the master is synchronous and paced by its SYNC period, so it runs on a dedicated
//! thread of the daemon rather than as async tasks, and stays identical to the virtual-bus
//! code path that the tests exercise.

use std::time::{Duration, Instant};

use socketcan::{CanSocket, EmbeddedFrame, Id, Socket, StandardId};

use super::{BusError, CanBus, CanFrame};

/// Linux errno: address family not supported by protocol.
const EAFNOSUPPORT: i32 = 97;
/// Linux errno: no such device.
const ENODEV: i32 = 19;

pub struct SocketCanBus {
    socket: CanSocket,
    name: String,
    opened: Instant,
}

impl SocketCanBus {
    /// Opens `interface` (e.g. `can0`, `vcan0`). Each failure names the interface and what is
    /// missing: the kernel's CAN address family (AF_CAN: no SocketCAN in this kernel, or its
    /// `can`/`can_raw` modules not loaded), the interface itself, or the OS reason.
    pub fn open(interface: &str) -> Result<Self, BusError> {
        let open_error = |reason: String| BusError::Open {
            bus: interface.to_owned(),
            reason,
        };
        // The kernel resolves the interface name before it creates a CAN socket, so a kernel
        // without CAN would report a missing interface; a socket bound to every interface
        // (index 0) asks for the address family alone first.
        if let Err(e) = CanSocket::open_iface(0) {
            return Err(open_error(match e.raw_os_error() {
                Some(EAFNOSUPPORT) => format!(
                    "this kernel has no SocketCAN: address family AF_CAN is not supported \
                     ({e}); load the modules (modprobe can can_raw, and vcan for a virtual \
                     interface) or use --hal can-emulated"
                ),
                _ => format!("cannot create an AF_CAN socket: {e}"),
            }));
        }
        let socket = CanSocket::open(interface).map_err(|e| {
            open_error(match e.raw_os_error() {
                Some(ENODEV) => format!(
                    "no such network interface ({e}); bring it up with `ip link` (see the \
                     README's kernel CAN section)"
                ),
                _ => e.to_string(),
            })
        })?;
        Ok(SocketCanBus {
            socket,
            name: interface.to_owned(),
            opened: Instant::now(),
        })
    }

    fn io_error(&self, e: std::io::Error) -> BusError {
        BusError::Io {
            bus: self.name.clone(),
            reason: e.to_string(),
        }
    }
}

impl CanBus for SocketCanBus {
    fn name(&self) -> &str {
        &self.name
    }

    fn now(&self) -> Duration {
        self.opened.elapsed()
    }

    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let id = StandardId::new(frame.id()).ok_or_else(|| BusError::Io {
            bus: self.name.clone(),
            reason: format!("identifier 0x{:X} is not standard", frame.id()),
        })?;
        let out = socketcan::CanFrame::new(id, frame.data()).ok_or_else(|| BusError::Io {
            bus: self.name.clone(),
            reason: "frame longer than 8 bytes".into(),
        })?;
        self.socket
            .write_frame_insist(&out)
            .map_err(|e| self.io_error(e))
    }

    /// Skips remote, error and extended-id frames: CANopen uses none of them.
    fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError> {
        loop {
            let Some(left) = deadline.checked_sub(self.now()).filter(|d| !d.is_zero()) else {
                return Ok(None);
            };
            match self.socket.read_frame_timeout(left) {
                Ok(socketcan::CanFrame::Data(frame)) => {
                    if let Id::Standard(id) = frame.id() {
                        if let Ok(frame) = CanFrame::new(id.as_raw(), frame.data()) {
                            return Ok(Some(frame));
                        }
                    }
                }
                Ok(_) => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.io_error(e)),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Needs a `vcan0` interface (`ip link add vcan0 type vcan && ip link set vcan0 up`).
    #[test]
    fn frames_cross_a_virtual_kernel_interface() {
        let (mut a, mut b) = match (SocketCanBus::open("vcan0"), SocketCanBus::open("vcan0")) {
            (Ok(a), Ok(b)) => (a, b),
            (Err(e), _) | (_, Err(e)) => {
                eprintln!("skipping: no SocketCAN interface vcan0 here: {e}");
                return;
            }
        };
        let frame = CanFrame::new(0x601, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap();
        a.send(&frame).unwrap();
        let deadline = b.now() + Duration::from_millis(500);
        assert_eq!(b.recv_until(deadline).unwrap(), Some(frame));
        let deadline = b.now() + Duration::from_millis(20);
        assert_eq!(b.recv_until(deadline).unwrap(), None);
    }

    /// Whether this kernel has SocketCAN loaded (its core creates `/proc/net/can`).
    fn kernel_has_can() -> bool {
        std::path::Path::new("/proc/net/can").exists()
    }

    #[test]
    fn opening_a_missing_interface_is_an_error_naming_it_and_what_is_missing() {
        let err = SocketCanBus::open("nosuchcan9").err().unwrap().to_string();
        assert!(err.contains("nosuchcan9"), "{err}");
        let missing = if kernel_has_can() {
            "no such network interface"
        } else {
            "AF_CAN"
        };
        assert!(err.contains(missing), "{err}");
    }
}
