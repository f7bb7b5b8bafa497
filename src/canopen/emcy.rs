//! EMCY consumer (CiA 301 §7.2.7): decode a drive's emergency frames into the error code with
//! its CiA 301 / CiA 402 text, the error register (0x1001) and the five manufacturer bytes.
//!
//! Frame layout, 8 bytes on COB-ID 0x080 + node: bytes 0–1 error code (LE), byte 2 error
//! register, bytes 3–7 manufacturer-specific. Code 0x0000 means "error reset or no error".
//! The frame codec is canopen-rs's `EmergencyMessage`; the texts are ours.

use canopen_rs::EmergencyMessage;
use std::fmt;
use thiserror::Error;

/// An emergency message from the drive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Emcy {
    /// The 16-bit emergency error code.
    pub code: u16,
    /// The error register (object 0x1001) when the message was sent.
    pub register: u8,
    /// Manufacturer-specific error field (bytes 3–7).
    pub manufacturer: [u8; 5],
}

/// Why an EMCY frame did not decode.
#[derive(Clone, Copy, Debug, Error, PartialEq, Eq)]
pub enum EmcyError {
    #[error("EMCY frame of {0} bytes: CiA 301 EMCY frames carry 8")]
    Length(usize),
}

impl Emcy {
    /// Decode the data field of an EMCY frame (exactly 8 bytes).
    pub fn decode(data: &[u8]) -> Result<Emcy, EmcyError> {
        let m = EmergencyMessage::decode(data).map_err(|_| EmcyError::Length(data.len()))?;
        Ok(Emcy {
            code: m.error_code,
            register: m.error_register.0,
            manufacturer: m.vendor_specific,
        })
    }

    /// The 8 bytes of this message.
    pub fn encode(&self) -> [u8; 8] {
        let mut p = [0u8; 8];
        p[0..2].copy_from_slice(&self.code.to_le_bytes());
        p[2] = self.register;
        p[3..8].copy_from_slice(&self.manufacturer);
        p
    }

    /// Whether this is the "error reset / no error" message (code 0x0000).
    pub fn is_reset(&self) -> bool {
        self.code == 0
    }

    /// The error code's text.
    pub fn text(&self) -> &'static str {
        error_code_text(self.code)
    }

    /// The set bits of the error register, as text.
    pub fn register_bits(&self) -> Vec<&'static str> {
        register_bits(self.register)
    }
}

impl fmt::Display for Emcy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "EMCY 0x{:04X} {}", self.code, self.text())?;
        write!(f, " (error register 0x{:02X}", self.register)?;
        let bits = self.register_bits();
        if !bits.is_empty() {
            write!(f, ": {}", bits.join(", "))?;
        }
        write!(f, "; manufacturer")?;
        for b in self.manufacturer {
            write!(f, " {b:02X}")?;
        }
        write!(f, ")")
    }
}

/// The error register's bits (CiA 301 §7.5.2.2), by name.
pub fn register_bits(reg: u8) -> Vec<&'static str> {
    const NAMES: [(u8, &str); 7] = [
        (0x01, "generic"),
        (0x02, "current"),
        (0x04, "voltage"),
        (0x08, "temperature"),
        (0x10, "communication"),
        (0x20, "device profile"),
        (0x80, "manufacturer"),
    ];
    NAMES
        .iter()
        .filter(|(b, _)| reg & b != 0)
        .map(|(_, n)| *n)
        .collect()
}

/// The text of an emergency error code: the exact CiA 301 / CiA 402 (IEC 61800-7-201) entry
/// when there is one, else the text of its class (high byte, then high nibble).
pub fn error_code_text(code: u16) -> &'static str {
    if let Some(t) = exact(code) {
        return t;
    }
    if let Some(t) = exact(code & 0xFF00) {
        return t;
    }
    match code >> 12 {
        0x0 => "error reset or no error",
        0x1 => "generic error",
        0x2 => "current",
        0x3 => "voltage",
        0x4 => "temperature",
        0x5 => "device hardware",
        0x6 => "device software",
        0x7 => "additional modules",
        0x8 => "monitoring",
        0x9 => "external error",
        0xF => "additional functions",
        _ => "unknown error code",
    }
}

fn exact(code: u16) -> Option<&'static str> {
    Some(match code {
        0x0000 => "error reset or no error",
        0x1000 => "generic error",
        0x2000 => "current",
        0x2100 => "current, device input side",
        0x2110 => "short circuit/earth leakage (input)",
        0x2200 => "current inside the device",
        0x2300 => "current, device output side",
        0x2310 => "continuous over-current",
        0x2311 => "continuous over-current no. 1",
        0x2312 => "continuous over-current no. 2",
        0x2320 => "short circuit/earth leakage (motor side)",
        0x2330 => "earth leakage (motor side)",
        0x2340 => "short circuit (motor side)",
        0x3000 => "voltage",
        0x3100 => "mains voltage",
        0x3110 => "mains over-voltage",
        0x3120 => "mains under-voltage",
        0x3130 => "phase failure",
        0x3200 => "voltage inside the device",
        0x3210 => "DC link over-voltage",
        0x3220 => "DC link under-voltage",
        0x3300 => "output voltage",
        0x4000 => "temperature",
        0x4100 => "ambient temperature",
        0x4200 => "device temperature",
        0x4210 => "excess temperature device",
        0x4300 => "drive temperature",
        0x4310 => "excess temperature drive",
        0x4400 => "supply temperature",
        0x5000 => "device hardware",
        0x5100 => "supply",
        0x5200 => "control",
        0x5300 => "operating unit",
        0x5400 => "power section",
        0x5500 => "communication (hardware)",
        0x5530 => "data storage (EEPROM)",
        0x6000 => "device software",
        0x6100 => "internal software",
        0x6200 => "user software",
        0x6300 => "data set",
        0x6320 => "parameter error",
        0x7000 => "additional modules",
        0x7100 => "power",
        0x7110 => "brake chopper",
        0x7120 => "motor",
        0x7121 => "motor blocked",
        0x7200 => "measurement circuit",
        0x7300 => "sensor",
        0x7303 => "resolver 1 fault",
        0x7304 => "resolver 2 fault",
        0x7305 => "incremental sensor 1 fault",
        0x7306 => "incremental sensor 2 fault",
        0x7310 => "speed",
        0x7320 => "position",
        0x7400 => "computation circuit",
        0x7500 => "communication",
        0x7600 => "data storage",
        0x8000 => "monitoring",
        0x8100 => "communication",
        0x8110 => "CAN overrun (objects lost)",
        0x8120 => "CAN in error passive mode",
        0x8130 => "life guard error or heartbeat error",
        0x8140 => "recovered from bus off",
        0x8150 => "CAN-ID collision",
        0x8200 => "protocol error",
        0x8210 => "PDO not processed due to length error",
        0x8220 => "PDO length exceeded",
        0x8230 => "DAM MPDO not processed, destination object not available",
        0x8240 => "unexpected SYNC data length",
        0x8250 => "RPDO timeout",
        0x8300 => "torque control",
        0x8311 => "excess torque",
        0x8400 => "velocity speed controller",
        0x8500 => "position controller",
        0x8600 => "positioning controller",
        0x8611 => "following error",
        0x8612 => "reference limit",
        0x8700 => "sync controller",
        0x8800 => "winding controller",
        0x9000 => "external error",
        0xF000 => "additional functions",
        0xF001 => "deceleration",
        0xF002 => "sub-synchronous run",
        0xF003 => "stroke operation",
        0xF004 => "control",
        0xFF00 => "device specific",
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Literal frames: code LE in bytes 0–1, register in byte 2, manufacturer bytes 3–7.
    #[test]
    fn decode_literal_frames() {
        // Following error (CiA 402 0x8611), register: generic + device profile (0x21).
        let e = Emcy::decode(&[0x11, 0x86, 0x21, 0x01, 0x02, 0x03, 0x04, 0x05]).unwrap();
        assert_eq!(e.code, 0x8611);
        assert_eq!(e.register, 0x21);
        assert_eq!(e.manufacturer, [1, 2, 3, 4, 5]);
        assert_eq!(e.text(), "following error");
        assert_eq!(e.register_bits(), vec!["generic", "device profile"]);
        assert_eq!(
            e.to_string(),
            "EMCY 0x8611 following error (error register 0x21: generic, device profile; manufacturer 01 02 03 04 05)"
        );
        assert_eq!(e.encode(), [0x11, 0x86, 0x21, 1, 2, 3, 4, 5]);

        // Sensor (0x7300), over-current (0x2310) with the current bit.
        let e = Emcy::decode(&[0x00, 0x73, 0x01, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(e.text(), "sensor");
        let e = Emcy::decode(&[0x10, 0x23, 0x03, 0, 0, 0, 0, 0xAA]).unwrap();
        assert_eq!(e.text(), "continuous over-current");
        assert_eq!(e.register_bits(), vec!["generic", "current"]);
        // Error reset.
        let e = Emcy::decode(&[0; 8]).unwrap();
        assert!(e.is_reset());
        assert_eq!(e.text(), "error reset or no error");
        assert_eq!(
            e.to_string(),
            "EMCY 0x0000 error reset or no error (error register 0x00; manufacturer 00 00 00 00 00)"
        );
        // Heartbeat error from the communication class.
        let e = Emcy::decode(&[0x30, 0x81, 0x11, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(e.text(), "life guard error or heartbeat error");
        assert_eq!(e.register_bits(), vec!["generic", "communication"]);
    }

    #[test]
    fn wrong_length_is_an_error() {
        assert_eq!(Emcy::decode(&[0x11, 0x86, 0x21]), Err(EmcyError::Length(3)));
        assert_eq!(Emcy::decode(&[0; 9]), Err(EmcyError::Length(9)));
    }

    #[test]
    fn unknown_codes_fall_back_to_their_class() {
        assert_eq!(error_code_text(0x8613), "positioning controller");
        assert_eq!(error_code_text(0x2399), "current, device output side");
        assert_eq!(error_code_text(0x42AB), "device temperature");
        assert_eq!(error_code_text(0x9ABC), "external error");
        assert_eq!(error_code_text(0xFF42), "device specific");
        assert_eq!(error_code_text(0xA000), "unknown error code");
        assert_eq!(error_code_text(0x0001), "error reset or no error");
    }
}
