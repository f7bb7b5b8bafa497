//! CiA 402 (IEC 61800-7-201) drive profile: statusword decoding into the power states of the
//! drive's finite state automaton (FSA), controlword commands, and the mode-specific bits of
//! homing (mode 6), profile position (mode 1) and cyclic synchronous position (mode 8).
//!
//! Cyclic synchronous position uses no mode-specific controlword bits; in its statusword bit 10
//! is reserved, bit 12 says whether the drive uses the target position (0x607A) as its position
//! demand (1) or ignores it (0), and bit 13 is the following error.
//!
//! Pure functions and plain values, shared by the master (which decodes statuswords and picks
//! controlwords) and the twin drive (which decodes controlwords and composes statuswords).

use std::fmt;

// --- Controlword (0x6040) bits ------------------------------------------------------------

/// Bit 0: switch on.
pub const CW_SWITCH_ON: u16 = 1 << 0;
/// Bit 1: enable voltage.
pub const CW_ENABLE_VOLTAGE: u16 = 1 << 1;
/// Bit 2: quick stop (active low: 0 requests a quick stop).
pub const CW_QUICK_STOP: u16 = 1 << 2;
/// Bit 3: enable operation.
pub const CW_ENABLE_OPERATION: u16 = 1 << 3;
/// Bit 4, profile position: new set-point; homing: start homing operation.
pub const CW_NEW_SETPOINT: u16 = 1 << 4;
/// Bit 4 in homing mode.
pub const CW_HOMING_START: u16 = 1 << 4;
/// Bit 5, profile position: change set immediately.
pub const CW_CHANGE_IMMEDIATELY: u16 = 1 << 5;
/// Bit 6, profile position: target is relative (1) or absolute (0).
pub const CW_RELATIVE: u16 = 1 << 6;
/// Bit 7: fault reset (acts on its rising edge).
pub const CW_FAULT_RESET: u16 = 1 << 7;
/// Bit 8: halt.
pub const CW_HALT: u16 = 1 << 8;
/// The bits that form the FSA command (0..=3 and 7).
pub const CW_COMMAND_MASK: u16 = 0x008F;

// --- Statusword (0x6041) bits -------------------------------------------------------------

/// Bit 0: ready to switch on.
pub const SW_READY_TO_SWITCH_ON: u16 = 1 << 0;
/// Bit 1: switched on.
pub const SW_SWITCHED_ON: u16 = 1 << 1;
/// Bit 2: operation enabled.
pub const SW_OPERATION_ENABLED: u16 = 1 << 2;
/// Bit 3: fault.
pub const SW_FAULT: u16 = 1 << 3;
/// Bit 4: voltage enabled.
pub const SW_VOLTAGE_ENABLED: u16 = 1 << 4;
/// Bit 5: quick stop (active low: 0 while a quick stop is active).
pub const SW_QUICK_STOP: u16 = 1 << 5;
/// Bit 6: switch on disabled.
pub const SW_SWITCH_ON_DISABLED: u16 = 1 << 6;
/// Bit 7: warning.
pub const SW_WARNING: u16 = 1 << 7;
/// Bit 9: remote (the controlword is processed).
pub const SW_REMOTE: u16 = 1 << 9;
/// Bit 10: target reached.
pub const SW_TARGET_REACHED: u16 = 1 << 10;
/// Bit 11: internal limit active.
pub const SW_INTERNAL_LIMIT: u16 = 1 << 11;
/// Bit 12, profile position: set-point acknowledge; homing: homing attained.
pub const SW_SETPOINT_ACK: u16 = 1 << 12;
/// Bit 12 in homing mode.
pub const SW_HOMING_ATTAINED: u16 = 1 << 12;
/// Bit 13, profile position: following error; homing: homing error.
pub const SW_FOLLOWING_ERROR: u16 = 1 << 13;
/// Bit 13 in homing mode.
pub const SW_HOMING_ERROR: u16 = 1 << 13;
/// Bit 12 in cyclic synchronous position mode: 1 = the target position is used as the
/// position demand, 0 = target position ignored (CiA 402 / IEC 61800-7-201, CSP).
pub const SW_CSP_TARGET_USED: u16 = 1 << 12;

// --- Modes of operation (0x6060 / 0x6061) -------------------------------------------------

/// Profile position mode.
pub const MODE_PROFILE_POSITION: i8 = 1;
/// Homing mode.
pub const MODE_HOMING: i8 = 6;
/// Cyclic synchronous position mode.
pub const MODE_CSP: i8 = 8;

/// A modes-of-operation value as text.
pub fn mode_name(mode: i8) -> &'static str {
    match mode {
        0 => "no mode",
        1 => "profile position",
        2 => "velocity",
        3 => "profile velocity",
        4 => "profile torque",
        6 => "homing",
        7 => "interpolated position",
        8 => "cyclic synchronous position",
        9 => "cyclic synchronous velocity",
        10 => "cyclic synchronous torque",
        m if m < 0 => "manufacturer-specific mode",
        _ => "reserved mode",
    }
}

/// The power states of the CiA 402 FSA.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PowerState {
    NotReadyToSwitchOn,
    SwitchOnDisabled,
    ReadyToSwitchOn,
    SwitchedOn,
    OperationEnabled,
    QuickStopActive,
    FaultReactionActive,
    Fault,
}

impl PowerState {
    /// Every state, in FSA order.
    pub const ALL: [PowerState; 8] = [
        PowerState::NotReadyToSwitchOn,
        PowerState::SwitchOnDisabled,
        PowerState::ReadyToSwitchOn,
        PowerState::SwitchedOn,
        PowerState::OperationEnabled,
        PowerState::QuickStopActive,
        PowerState::FaultReactionActive,
        PowerState::Fault,
    ];

    /// Decode a statusword (CiA 402 table "state coding"): bits 0–3, 5 and 6 select the
    /// state; `None` for a combination the profile does not define.
    ///
    /// | state | mask | value |
    /// |---|---|---|
    /// | not ready to switch on | 0x4F | 0x00 |
    /// | switch on disabled | 0x4F | 0x40 |
    /// | ready to switch on | 0x6F | 0x21 |
    /// | switched on | 0x6F | 0x23 |
    /// | operation enabled | 0x6F | 0x27 |
    /// | quick stop active | 0x6F | 0x07 |
    /// | fault reaction active | 0x4F | 0x0F |
    /// | fault | 0x4F | 0x08 |
    pub fn from_statusword(sw: u16) -> Option<PowerState> {
        Some(match (sw & 0x4F, sw & 0x6F) {
            (0x00, _) => PowerState::NotReadyToSwitchOn,
            (0x40, _) => PowerState::SwitchOnDisabled,
            (_, 0x21) => PowerState::ReadyToSwitchOn,
            (_, 0x23) => PowerState::SwitchedOn,
            (_, 0x27) => PowerState::OperationEnabled,
            (_, 0x07) => PowerState::QuickStopActive,
            (0x0F, _) => PowerState::FaultReactionActive,
            (0x08, _) => PowerState::Fault,
            _ => return None,
        })
    }

    /// The statusword bits 0–6 that a drive reports in this state (the canonical values of
    /// the table above, with bit 5 "quick stop" set where it is a don't-care).
    pub fn statusword_bits(self) -> u16 {
        match self {
            PowerState::NotReadyToSwitchOn => 0x0000,
            PowerState::SwitchOnDisabled => 0x0040,
            PowerState::ReadyToSwitchOn => 0x0021,
            PowerState::SwitchedOn => 0x0023,
            PowerState::OperationEnabled => 0x0027,
            PowerState::QuickStopActive => 0x0007,
            PowerState::FaultReactionActive => 0x000F,
            PowerState::Fault => 0x0008,
        }
    }

    /// The state's name as CiA 402 writes it.
    pub fn name(self) -> &'static str {
        match self {
            PowerState::NotReadyToSwitchOn => "not ready to switch on",
            PowerState::SwitchOnDisabled => "switch on disabled",
            PowerState::ReadyToSwitchOn => "ready to switch on",
            PowerState::SwitchedOn => "switched on",
            PowerState::OperationEnabled => "operation enabled",
            PowerState::QuickStopActive => "quick stop active",
            PowerState::FaultReactionActive => "fault reaction active",
            PowerState::Fault => "fault",
        }
    }

    /// The state's name as CiA 402 writes it (a capital first letter), for the snapshot and
    /// the console: "Operation enabled".
    pub fn label(self) -> &'static str {
        match self {
            PowerState::NotReadyToSwitchOn => "Not ready to switch on",
            PowerState::SwitchOnDisabled => "Switch on disabled",
            PowerState::ReadyToSwitchOn => "Ready to switch on",
            PowerState::SwitchedOn => "Switched on",
            PowerState::OperationEnabled => "Operation enabled",
            PowerState::QuickStopActive => "Quick stop active",
            PowerState::FaultReactionActive => "Fault reaction active",
            PowerState::Fault => "Fault",
        }
    }

    /// Whether the drive is in (or entering) its fault state.
    pub fn is_fault(self) -> bool {
        matches!(self, PowerState::Fault | PowerState::FaultReactionActive)
    }
}

impl fmt::Display for PowerState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A statusword with its bits named.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Statusword(pub u16);

impl Statusword {
    pub fn state(self) -> Option<PowerState> {
        PowerState::from_statusword(self.0)
    }
    fn bit(self, b: u16) -> bool {
        self.0 & b != 0
    }
    pub fn voltage_enabled(self) -> bool {
        self.bit(SW_VOLTAGE_ENABLED)
    }
    pub fn warning(self) -> bool {
        self.bit(SW_WARNING)
    }
    pub fn remote(self) -> bool {
        self.bit(SW_REMOTE)
    }
    pub fn target_reached(self) -> bool {
        self.bit(SW_TARGET_REACHED)
    }
    pub fn internal_limit(self) -> bool {
        self.bit(SW_INTERNAL_LIMIT)
    }
    /// Profile position: set-point acknowledge (bit 12).
    pub fn setpoint_ack(self) -> bool {
        self.bit(SW_SETPOINT_ACK)
    }
    /// Profile position and cyclic synchronous position: following error (bit 13).
    pub fn following_error(self) -> bool {
        self.bit(SW_FOLLOWING_ERROR)
    }
    /// Cyclic synchronous position: the drive uses the target position (bit 12).
    pub fn csp_target_used(self) -> bool {
        self.bit(SW_CSP_TARGET_USED)
    }
    /// Homing mode: bits 13, 12 and 10 decoded.
    pub fn homing(self) -> HomingStatus {
        HomingStatus::from_statusword(self.0)
    }
}

/// Homing status from statusword bits 13 (homing error), 12 (homing attained) and 10 (target
/// reached), per the CiA 402 homing-mode table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HomingStatus {
    /// 0 0 0: homing procedure in progress.
    InProgress,
    /// 0 0 1: homing procedure interrupted or not started.
    Interrupted,
    /// 0 1 0: homing attained, target not reached.
    AttainedNotReached,
    /// 0 1 1: homing procedure completed successfully.
    Completed,
    /// 1 0 0: homing error, velocity not 0.
    ErrorMoving,
    /// 1 0 1: homing error, velocity 0.
    ErrorStopped,
    /// 1 1 x: reserved.
    Reserved,
}

impl std::fmt::Display for HomingStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            HomingStatus::InProgress => "homing still in progress",
            HomingStatus::Interrupted => "homing interrupted or not started",
            HomingStatus::AttainedNotReached => "home attained, target not reached",
            HomingStatus::Completed => "homing completed",
            HomingStatus::ErrorMoving => "homing error with the stage moving",
            HomingStatus::ErrorStopped => "homing error with the stage stopped",
            HomingStatus::Reserved => "a reserved homing status",
        })
    }
}

impl HomingStatus {
    pub fn from_statusword(sw: u16) -> HomingStatus {
        let e = sw & SW_HOMING_ERROR != 0;
        let a = sw & SW_HOMING_ATTAINED != 0;
        let r = sw & SW_TARGET_REACHED != 0;
        match (e, a, r) {
            (false, false, false) => HomingStatus::InProgress,
            (false, false, true) => HomingStatus::Interrupted,
            (false, true, false) => HomingStatus::AttainedNotReached,
            (false, true, true) => HomingStatus::Completed,
            (true, false, false) => HomingStatus::ErrorMoving,
            (true, false, true) => HomingStatus::ErrorStopped,
            (true, true, _) => HomingStatus::Reserved,
        }
    }

    /// The statusword bits 10, 12, 13 of this status (`Reserved` reports 0x3000).
    pub fn bits(self) -> u16 {
        match self {
            HomingStatus::InProgress => 0,
            HomingStatus::Interrupted => SW_TARGET_REACHED,
            HomingStatus::AttainedNotReached => SW_HOMING_ATTAINED,
            HomingStatus::Completed => SW_HOMING_ATTAINED | SW_TARGET_REACHED,
            HomingStatus::ErrorMoving => SW_HOMING_ERROR,
            HomingStatus::ErrorStopped => SW_HOMING_ERROR | SW_TARGET_REACHED,
            HomingStatus::Reserved => SW_HOMING_ERROR | SW_HOMING_ATTAINED,
        }
    }

    pub fn is_error(self) -> bool {
        matches!(
            self,
            HomingStatus::ErrorMoving | HomingStatus::ErrorStopped | HomingStatus::Reserved
        )
    }
}

/// The FSA commands a controlword carries (CiA 402 "command coding", bits 7, 3, 2, 1, 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FsaCommand {
    /// 0 x 1 1 0: transitions 2, 6, 8.
    Shutdown,
    /// 0 0 1 1 1: transition 3 (also "disable operation", transition 5).
    SwitchOn,
    /// 0 1 1 1 1: transitions 3+4, 4 and 16.
    EnableOperation,
    /// 0 x x 0 x: transitions 7, 9, 10, 12.
    DisableVoltage,
    /// 0 x 0 1 x: transitions 7, 10, 11.
    QuickStop,
    /// Rising edge of bit 7: transition 15 (the other bits are ignored while bit 7 is set).
    FaultReset,
}

impl FsaCommand {
    /// The command's canonical controlword bits 0–3 and 7.
    pub fn bits(self) -> u16 {
        match self {
            FsaCommand::Shutdown => 0x0006,
            FsaCommand::SwitchOn => 0x0007,
            FsaCommand::EnableOperation => 0x000F,
            FsaCommand::DisableVoltage => 0x0000,
            FsaCommand::QuickStop => 0x0002,
            FsaCommand::FaultReset => 0x0080,
        }
    }

    /// Decode the command a drive sees in `cw`, given the previous controlword `prev` (for the
    /// rising edge of bit 7). While bit 7 stays set no command is decoded.
    pub fn decode(cw: u16, prev: u16) -> Option<FsaCommand> {
        if cw & CW_FAULT_RESET != 0 {
            return (prev & CW_FAULT_RESET == 0).then_some(FsaCommand::FaultReset);
        }
        if cw & CW_ENABLE_VOLTAGE == 0 {
            return Some(FsaCommand::DisableVoltage);
        }
        if cw & CW_QUICK_STOP == 0 {
            return Some(FsaCommand::QuickStop);
        }
        if cw & CW_SWITCH_ON == 0 {
            return Some(FsaCommand::Shutdown);
        }
        Some(if cw & CW_ENABLE_OPERATION == 0 {
            FsaCommand::SwitchOn
        } else {
            FsaCommand::EnableOperation
        })
    }

    /// With the controlword's non-command bits (4–6, 8–15) from `cw` kept.
    pub fn apply_to(self, cw: u16) -> u16 {
        (cw & !CW_COMMAND_MASK) | self.bits()
    }
}

/// What the master should do next to bring a drive from `from` toward `to`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NextStep {
    /// Already there.
    Done,
    /// Send this command.
    Send(FsaCommand),
    /// The drive moves on by itself (not ready → switch on disabled, fault reaction → fault).
    Wait,
    /// No controlword leads there: the drive is in fault (a fault reset is needed first), or
    /// the target can only be entered by the drive itself.
    Blocked,
}

/// The next command on the shortest FSA path from `from` to `to` (the master's side of the
/// CiA 402 transitions). Fault is left only by an explicit fault reset, never implicitly.
pub fn next_step(from: PowerState, to: PowerState) -> NextStep {
    use FsaCommand as C;
    use PowerState as S;
    if from == to {
        return NextStep::Done;
    }
    match (from, to) {
        (_, S::NotReadyToSwitchOn | S::FaultReactionActive | S::Fault) => NextStep::Blocked,
        (S::Fault, _) => NextStep::Blocked,
        (S::NotReadyToSwitchOn | S::FaultReactionActive, _) => NextStep::Wait,
        (_, S::SwitchOnDisabled) => NextStep::Send(C::DisableVoltage),
        (S::OperationEnabled, S::QuickStopActive) => NextStep::Send(C::QuickStop),
        // Quick stop active is entered only from operation enabled: get there first.
        (_, S::QuickStopActive) => next_step(from, S::OperationEnabled),
        (S::QuickStopActive, S::OperationEnabled) => NextStep::Send(C::EnableOperation),
        (S::QuickStopActive, _) => NextStep::Send(C::DisableVoltage),
        (S::SwitchOnDisabled, _) => NextStep::Send(C::Shutdown),
        (_, S::ReadyToSwitchOn) => NextStep::Send(C::Shutdown),
        (S::ReadyToSwitchOn, _) => NextStep::Send(C::SwitchOn),
        (S::SwitchedOn, S::OperationEnabled) => NextStep::Send(C::EnableOperation),
        (S::OperationEnabled, S::SwitchedOn) => NextStep::Send(C::SwitchOn),
        (S::SwitchedOn | S::OperationEnabled, _) => NextStep::Blocked,
    }
}

/// The state a drive enters when it receives `cmd` in `from` (the device side of the FSA).
/// `None`: the command causes no transition there. Quick stop from operation enabled enters
/// quick stop active; leaving it is the drive's own business (option code 0x605A).
pub fn transition(from: PowerState, cmd: FsaCommand) -> Option<PowerState> {
    use FsaCommand as C;
    use PowerState as S;
    Some(match (from, cmd) {
        (S::Fault, C::FaultReset) => S::SwitchOnDisabled, // 15
        (S::SwitchOnDisabled, C::Shutdown) => S::ReadyToSwitchOn, // 2
        (S::ReadyToSwitchOn, C::SwitchOn) => S::SwitchedOn, // 3
        (S::ReadyToSwitchOn, C::EnableOperation) => S::OperationEnabled, // 3 + 4
        (S::ReadyToSwitchOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled, // 7
        (S::SwitchedOn, C::EnableOperation) => S::OperationEnabled, // 4
        (S::SwitchedOn, C::Shutdown) => S::ReadyToSwitchOn, // 6
        (S::SwitchedOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled, // 10
        (S::OperationEnabled, C::SwitchOn) => S::SwitchedOn, // 5
        (S::OperationEnabled, C::Shutdown) => S::ReadyToSwitchOn, // 8
        (S::OperationEnabled, C::DisableVoltage) => S::SwitchOnDisabled, // 9
        (S::OperationEnabled, C::QuickStop) => S::QuickStopActive, // 11
        (S::QuickStopActive, C::DisableVoltage) => S::SwitchOnDisabled, // 12
        (S::QuickStopActive, C::EnableOperation) => S::OperationEnabled, // 16
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every state from its canonical pattern, and with the don't-care bits (4 voltage, 7
    /// warning, 9 remote, 10–15 mode-specific) all set: the decoding ignores them.
    #[test]
    fn statusword_decoding_table() {
        let table: [(u16, PowerState); 8] = [
            (0x0000, PowerState::NotReadyToSwitchOn),
            (0x0040, PowerState::SwitchOnDisabled),
            (0x0021, PowerState::ReadyToSwitchOn),
            (0x0023, PowerState::SwitchedOn),
            (0x0027, PowerState::OperationEnabled),
            (0x0007, PowerState::QuickStopActive),
            (0x000F, PowerState::FaultReactionActive),
            (0x0008, PowerState::Fault),
        ];
        for (sw, st) in table {
            assert_eq!(PowerState::from_statusword(sw), Some(st), "{sw:#06x}");
            assert_eq!(
                PowerState::from_statusword(sw | 0xFE90),
                Some(st),
                "{sw:#06x} with don't-care bits"
            );
            assert_eq!(PowerState::from_statusword(st.statusword_bits()), Some(st));
        }
        // Bit 5 is a don't-care in the four states whose mask is 0x4F.
        assert_eq!(
            PowerState::from_statusword(0x0060),
            Some(PowerState::SwitchOnDisabled)
        );
        assert_eq!(PowerState::from_statusword(0x0028), Some(PowerState::Fault));
        assert_eq!(
            PowerState::from_statusword(0x002F),
            Some(PowerState::FaultReactionActive)
        );
        // Typical real values: 0x0250 SOD with voltage + remote, 0x1637 enabled + ack.
        assert_eq!(
            Statusword(0x0250).state(),
            Some(PowerState::SwitchOnDisabled)
        );
        assert_eq!(
            Statusword(0x1637).state(),
            Some(PowerState::OperationEnabled)
        );
        // Undefined patterns.
        for sw in [0x0001u16, 0x0003, 0x0041, 0x0047, 0x0004, 0x0025] {
            assert_eq!(PowerState::from_statusword(sw), None, "{sw:#06x}");
        }
        // Every one of the 128 patterns of bits 0..=6 decodes to at most one state.
        let mut defined = 0;
        for sw in 0u16..0x80 {
            if let Some(st) = PowerState::from_statusword(sw) {
                defined += 1;
                assert_eq!(sw & 0x4F, st.statusword_bits() & 0x4F);
            }
        }
        // Mask 0x4F leaves bits 4 and 5 free (4 patterns per state), mask 0x6F bit 4 (2).
        assert_eq!(defined, 4 * 4 + 4 * 2);
    }

    #[test]
    fn named_bits() {
        let sw = Statusword(0x3637);
        assert!(sw.voltage_enabled() && sw.remote() && sw.target_reached());
        assert!(sw.setpoint_ack() && sw.following_error() && !sw.warning());
        assert!(!sw.internal_limit());
        assert!(Statusword(0x0800).internal_limit());
    }

    #[test]
    fn homing_status_table() {
        let t = [
            (0x0000, HomingStatus::InProgress),
            (0x0400, HomingStatus::Interrupted),
            (0x1000, HomingStatus::AttainedNotReached),
            (0x1400, HomingStatus::Completed),
            (0x2000, HomingStatus::ErrorMoving),
            (0x2400, HomingStatus::ErrorStopped),
            (0x3000, HomingStatus::Reserved),
            (0x3400, HomingStatus::Reserved),
        ];
        for (bits, st) in t {
            assert_eq!(
                HomingStatus::from_statusword(0x0237 | bits),
                st,
                "{bits:#06x}"
            );
            if st != HomingStatus::Reserved {
                assert_eq!(st.bits(), bits);
            }
        }
        assert!(HomingStatus::ErrorStopped.is_error() && !HomingStatus::Completed.is_error());
    }

    #[test]
    fn controlword_commands_encode_and_decode() {
        use FsaCommand as C;
        assert_eq!(C::Shutdown.bits(), 0x06);
        assert_eq!(C::SwitchOn.bits(), 0x07);
        assert_eq!(C::EnableOperation.bits(), 0x0F);
        assert_eq!(C::DisableVoltage.bits(), 0x00);
        assert_eq!(C::QuickStop.bits(), 0x02);
        assert_eq!(C::FaultReset.bits(), 0x80);
        for c in [
            C::Shutdown,
            C::SwitchOn,
            C::EnableOperation,
            C::DisableVoltage,
            C::QuickStop,
        ] {
            assert_eq!(C::decode(c.bits(), 0), Some(c));
            // Mode bits (4–6, 8) do not change the command.
            assert_eq!(C::decode(c.bits() | 0x0170, 0), Some(c));
        }
        // Don't-care bits of the command table.
        assert_eq!(C::decode(0x000E, 0), Some(C::Shutdown)); // 0 1 1 1 0
        assert_eq!(C::decode(0x0005, 0), Some(C::DisableVoltage)); // x x 0 x
        assert_eq!(C::decode(0x000B, 0), Some(C::QuickStop)); // x 0 1 x
        // Fault reset acts on the rising edge of bit 7 only.
        assert_eq!(C::decode(0x0080, 0x0000), Some(C::FaultReset));
        assert_eq!(C::decode(0x0080, 0x0080), None);
        assert_eq!(C::decode(0x008F, 0x000F), Some(C::FaultReset));
        // apply_to keeps the mode bits (4–6, 8) and replaces bits 0–3 and 7.
        assert_eq!(C::EnableOperation.apply_to(0x01F0), 0x017F);
        assert_eq!(C::QuickStop.apply_to(0x009F), 0x0012);
    }

    /// The master's path finder walks the FSA: from switch on disabled to operation enabled
    /// is shutdown, switch on, enable operation (transitions 2, 3, 4).
    #[test]
    fn controlword_sequences() {
        use FsaCommand as C;
        use PowerState as S;
        let walk = |from: S, to: S| {
            let mut s = from;
            let mut cmds = vec![];
            for _ in 0..8 {
                match next_step(s, to) {
                    NextStep::Done => return Some(cmds),
                    NextStep::Send(c) => {
                        cmds.push(c);
                        s = transition(s, c)?;
                    }
                    NextStep::Wait | NextStep::Blocked => return None,
                }
            }
            None
        };
        assert_eq!(
            walk(S::SwitchOnDisabled, S::OperationEnabled),
            Some(vec![C::Shutdown, C::SwitchOn, C::EnableOperation])
        );
        assert_eq!(
            walk(S::QuickStopActive, S::OperationEnabled),
            Some(vec![C::EnableOperation])
        );
        assert_eq!(
            walk(S::OperationEnabled, S::SwitchOnDisabled),
            Some(vec![C::DisableVoltage])
        );
        assert_eq!(
            walk(S::OperationEnabled, S::ReadyToSwitchOn),
            Some(vec![C::Shutdown])
        );
        assert_eq!(
            walk(S::OperationEnabled, S::SwitchedOn),
            Some(vec![C::SwitchOn])
        );
        assert_eq!(
            walk(S::OperationEnabled, S::QuickStopActive),
            Some(vec![C::QuickStop])
        );
        assert_eq!(
            walk(S::ReadyToSwitchOn, S::QuickStopActive),
            Some(vec![C::SwitchOn, C::EnableOperation, C::QuickStop])
        );
        assert_eq!(
            walk(S::SwitchedOn, S::ReadyToSwitchOn),
            Some(vec![C::Shutdown])
        );
        // Every reachable pair terminates (no cycles) from every non-fault state.
        for from in PowerState::ALL {
            for to in [
                S::SwitchOnDisabled,
                S::ReadyToSwitchOn,
                S::SwitchedOn,
                S::OperationEnabled,
                S::QuickStopActive,
            ] {
                let r = walk(from, to);
                match from {
                    S::Fault | S::NotReadyToSwitchOn | S::FaultReactionActive => {
                        assert!(r.is_none())
                    }
                    _ => assert!(r.is_some(), "{from:?} → {to:?}"),
                }
            }
        }
        assert_eq!(next_step(S::Fault, S::OperationEnabled), NextStep::Blocked);
        assert_eq!(
            next_step(S::FaultReactionActive, S::Fault),
            NextStep::Blocked
        );
        assert_eq!(
            next_step(S::NotReadyToSwitchOn, S::OperationEnabled),
            NextStep::Wait
        );
        assert_eq!(
            transition(S::Fault, C::FaultReset),
            Some(S::SwitchOnDisabled)
        );
        assert_eq!(transition(S::Fault, C::EnableOperation), None);
        assert_eq!(transition(S::SwitchOnDisabled, C::EnableOperation), None);
    }

    #[test]
    fn mode_names() {
        assert_eq!(mode_name(MODE_PROFILE_POSITION), "profile position");
        assert_eq!(mode_name(MODE_HOMING), "homing");
        assert_eq!(mode_name(MODE_CSP), "cyclic synchronous position");
        assert!(Statusword(0x1237).csp_target_used() && !Statusword(0x0237).csp_target_used());
        assert_eq!(mode_name(-3), "manufacturer-specific mode");
    }
}
