//! The CiA 402 power-drive state machine from both sides: the statusword a drive reports per
//! state and the transition a controlword causes (used by the emulated drive), and the
//! controlword a master sends to walk a drive towards Operation Enabled or out of Fault. Also
//! the object indices and PDO layouts master and emulated drive agree on.

use super::protocol::MapEntry;

pub const DEVICE_TYPE: u16 = 0x1000;
pub const ERROR_REGISTER: u16 = 0x1001;
pub const HEARTBEAT_PRODUCER: u16 = 0x1017;
pub const RPDO_COMM: u16 = 0x1400;
pub const RPDO_MAP: u16 = 0x1600;
pub const TPDO_COMM: u16 = 0x1800;
pub const TPDO_MAP: u16 = 0x1A00;
pub const ERROR_CODE: u16 = 0x603F;
pub const CONTROLWORD: u16 = 0x6040;
pub const STATUSWORD: u16 = 0x6041;
pub const MODES_OF_OPERATION: u16 = 0x6060;
pub const MODES_DISPLAY: u16 = 0x6061;
pub const POSITION_ACTUAL: u16 = 0x6064;
pub const VELOCITY_ACTUAL: u16 = 0x606C;
pub const TORQUE_ACTUAL: u16 = 0x6077;
pub const TARGET_POSITION: u16 = 0x607A;
pub const TARGET_VELOCITY: u16 = 0x60FF;

/// Device type 0x1000 of a CiA 402 drive: profile number 402 in the low 16 bits.
pub const CIA402_PROFILE: u32 = 402;
/// PDO COB-ID bit 31: the PDO does not exist (must be set while the mapping changes).
pub const PDO_INVALID: u32 = 0x8000_0000;
/// Transmission type "synchronous, every SYNC".
pub const TRANSMISSION_SYNC: u8 = 1;

const fn entry(index: u16, bits: u8) -> MapEntry {
    MapEntry {
        index,
        sub: 0,
        bits,
    }
}

/// RPDO1 in cyclic synchronous position mode: controlword, target position (counts).
pub const RPDO_CSP: [MapEntry; 2] = [entry(CONTROLWORD, 16), entry(TARGET_POSITION, 32)];
/// RPDO1 in cyclic synchronous velocity mode: controlword, target velocity (counts/s).
pub const RPDO_CSV: [MapEntry; 2] = [entry(CONTROLWORD, 16), entry(TARGET_VELOCITY, 32)];
/// TPDO1: statusword, actual position (counts). Position and velocity with the statusword do
/// not fit one 8-byte frame, so they are split over two TPDOs sent on the same SYNC.
pub const TPDO1: [MapEntry; 2] = [entry(STATUSWORD, 16), entry(POSITION_ACTUAL, 32)];
/// TPDO2: actual velocity (counts/s), actual torque (‰ of rated torque).
pub const TPDO2: [MapEntry; 2] = [entry(VELOCITY_ACTUAL, 32), entry(TORQUE_ACTUAL, 16)];

/// The CiA 402 mode of operation (object 0x6060) this crate drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OperationMode {
    /// Cyclic synchronous position (8): arm joints.
    Csp,
    /// Cyclic synchronous velocity (9): wheels.
    Csv,
}

impl OperationMode {
    pub fn code(self) -> i8 {
        match self {
            OperationMode::Csp => 8,
            OperationMode::Csv => 9,
        }
    }

    pub fn from_code(code: i8) -> Option<Self> {
        match code {
            8 => Some(OperationMode::Csp),
            9 => Some(OperationMode::Csv),
            _ => None,
        }
    }

    pub fn rpdo(self) -> &'static [MapEntry; 2] {
        match self {
            OperationMode::Csp => &RPDO_CSP,
            OperationMode::Csv => &RPDO_CSV,
        }
    }
}

/// States of the CiA 402 power-drive state machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cia402State {
    NotReadyToSwitchOn,
    SwitchOnDisabled,
    ReadyToSwitchOn,
    SwitchedOn,
    OperationEnabled,
    QuickStopActive,
    FaultReactionActive,
    Fault,
}

/// Statusword bit 9: the drive accepts controlword commands from the bus.
const REMOTE: u16 = 1 << 9;
/// Controlword bit 7: fault reset, acts on its rising edge.
pub const FAULT_RESET: u16 = 0x0080;
pub const SHUTDOWN: u16 = 0x0006;
pub const SWITCH_ON: u16 = 0x0007;
pub const ENABLE_OPERATION: u16 = 0x000F;
pub const DISABLE_VOLTAGE: u16 = 0x0000;

impl Cia402State {
    /// Decodes the state bits of a statusword (CiA 402 table of statusword patterns).
    pub fn from_statusword(sw: u16) -> Option<Self> {
        use Cia402State::*;
        match (sw & 0x4F, sw & 0x6F) {
            (0x00, _) => Some(NotReadyToSwitchOn),
            (0x40, _) => Some(SwitchOnDisabled),
            (0x0F, _) => Some(FaultReactionActive),
            (0x08, _) => Some(Fault),
            (_, 0x21) => Some(ReadyToSwitchOn),
            (_, 0x23) => Some(SwitchedOn),
            (_, 0x27) => Some(OperationEnabled),
            (_, 0x07) => Some(QuickStopActive),
            _ => None,
        }
    }

    /// The statusword a drive reports in this state (voltage enabled while switched on).
    pub fn statusword(self) -> u16 {
        use Cia402State::*;
        REMOTE
            | match self {
                NotReadyToSwitchOn => 0x00,
                SwitchOnDisabled => 0x40,
                ReadyToSwitchOn => 0x21,
                SwitchedOn => 0x33,
                OperationEnabled => 0x37,
                QuickStopActive => 0x17,
                FaultReactionActive => 0x1F,
                Fault => 0x08,
            }
    }

    /// The drive's transition on a new controlword (`previous` detects the fault-reset edge).
    pub fn on_controlword(self, previous: u16, cw: u16) -> Self {
        use Cia402State::*;
        let command = cw & 0x8F;
        let disable_voltage = cw & 0x02 == 0;
        let quick_stop = cw & 0x06 == 0x02;
        match self {
            Fault if cw & FAULT_RESET != 0 && previous & FAULT_RESET == 0 => SwitchOnDisabled,
            Fault | FaultReactionActive | NotReadyToSwitchOn => self,
            _ if disable_voltage => SwitchOnDisabled,
            OperationEnabled if quick_stop => QuickStopActive,
            _ if quick_stop => SwitchOnDisabled,
            SwitchOnDisabled if command & 0x07 == SHUTDOWN => ReadyToSwitchOn,
            ReadyToSwitchOn if command == SWITCH_ON => SwitchedOn,
            ReadyToSwitchOn if command == ENABLE_OPERATION => OperationEnabled,
            SwitchedOn if command == ENABLE_OPERATION => OperationEnabled,
            SwitchedOn | OperationEnabled if command & 0x07 == SHUTDOWN => ReadyToSwitchOn,
            OperationEnabled if command == SWITCH_ON => SwitchedOn,
            _ => self,
        }
    }
}

/// The controlword a master sends to move a drive one step towards its goal: Operation
/// Enabled when `enable`, else Ready to Switch On (torque off, quickly re-enabled). In Fault it
/// toggles the fault-reset bit when `reset` is requested, since the drive acts on the edge.
pub fn next_controlword(state: Option<Cia402State>, enable: bool, reset: bool, last: u16) -> u16 {
    use Cia402State::*;
    match state {
        Some(Fault) if reset && last & FAULT_RESET == 0 => FAULT_RESET,
        Some(Fault | FaultReactionActive) | None | Some(NotReadyToSwitchOn) => DISABLE_VOLTAGE,
        Some(QuickStopActive) => DISABLE_VOLTAGE,
        Some(SwitchOnDisabled) => SHUTDOWN,
        Some(ReadyToSwitchOn) if enable => SWITCH_ON,
        Some(SwitchedOn | OperationEnabled) if enable => ENABLE_OPERATION,
        Some(ReadyToSwitchOn | SwitchedOn | OperationEnabled) => SHUTDOWN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use Cia402State::*;

    const ALL: [Cia402State; 8] = [
        NotReadyToSwitchOn,
        SwitchOnDisabled,
        ReadyToSwitchOn,
        SwitchedOn,
        OperationEnabled,
        QuickStopActive,
        FaultReactionActive,
        Fault,
    ];

    #[test]
    fn statusword_round_trips() {
        for state in ALL {
            assert_eq!(
                Cia402State::from_statusword(state.statusword()),
                Some(state)
            );
        }
        assert_eq!(Cia402State::from_statusword(0x0237), Some(OperationEnabled));
        assert_eq!(Cia402State::from_statusword(0x0001), None);
    }

    /// Following the master's controlword from every state reaches the goal in ≤ 4 steps.
    #[test]
    fn master_controlwords_reach_the_goal() {
        for start in ALL {
            if matches!(start, FaultReactionActive | NotReadyToSwitchOn) {
                continue; // the drive leaves these on its own
            }
            for (enable, goal) in [(true, OperationEnabled), (false, ReadyToSwitchOn)] {
                let (mut state, mut last) = (start, 0);
                for _ in 0..5 {
                    let cw = next_controlword(Some(state), enable, true, last);
                    state = state.on_controlword(last, cw);
                    last = cw;
                }
                assert_eq!(state, goal, "from {start:?}, enable {enable}");
            }
        }
    }

    #[test]
    fn fault_reset_needs_a_rising_edge() {
        assert_eq!(Fault.on_controlword(FAULT_RESET, FAULT_RESET), Fault);
        assert_eq!(Fault.on_controlword(0, FAULT_RESET), SwitchOnDisabled);
        assert_eq!(Fault.on_controlword(0, ENABLE_OPERATION), Fault);
        // Without a reset request the master leaves a faulted drive alone.
        assert_eq!(
            next_controlword(Some(Fault), true, false, 0),
            DISABLE_VOLTAGE
        );
    }
}
