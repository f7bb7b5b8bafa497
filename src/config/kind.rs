//! Which kind of file `axiscomp check` was given: the service's configuration, the twin's,
//! an I/O map, a CNC map, an optical layout or a calibration. Each has its own reader; the
//! kind is told by the tables and keys only that kind has, so a file meant for another
//! command is named as such instead of failing on its first unknown key.

/// A configuration-like file's kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// `axiscomp serve --config` (`[io]`, `[head]`, …).
    Service,
    /// `axiscomp sim --config` (`[twin]`).
    Twin,
    /// An I/O module's register map (`plc-maps/io`: `register`, `block_start`).
    IoMap,
    /// A CNC's compensation-table map (`plc-maps/cnc`: `[handshake]`, `[payload]`).
    CncMap,
    /// The optical head's layout (`configs/optics`: `travel_axis`, `reading_paths`).
    Layout,
    /// A calibration file (`calibrate fit` writes it: `[meta]` and `[linear]`).
    Calibration,
}

impl FileKind {
    /// The kind in words, with the command that reads it.
    pub fn describe(self) -> &'static str {
        match self {
            FileKind::Service => "the service's configuration (axiscomp serve --config)",
            FileKind::Twin => "the digital twin's configuration (axiscomp sim --config)",
            FileKind::IoMap => "an I/O module's register map ([io] map)",
            FileKind::CncMap => "a CNC's compensation-table map ([plc] map)",
            FileKind::Layout => "an optical head layout ([head] layout)",
            FileKind::Calibration => "a calibration file ([head] calibration)",
        }
    }
}

/// The kind of the TOML `text`; `None` when it is not TOML (the service's reader then says
/// where the syntax breaks). A file with none of the marks is taken for the service's.
pub fn detect(text: &str) -> Option<FileKind> {
    let t: toml::Table = text.parse().ok()?;
    let has = |k: &str| t.contains_key(k);
    Some(if has("twin") {
        FileKind::Twin
    } else if has("handshake") || has("payload") {
        FileKind::CncMap
    } else if has("register") && has("block_start") {
        FileKind::IoMap
    } else if has("travel_axis") || has("reading_paths") || has("elements") {
        FileKind::Layout
    } else if has("meta") && has("linear") {
        FileKind::Calibration
    } else {
        FileKind::Service
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_files_are_told_apart() {
        let root = env!("CARGO_MANIFEST_DIR");
        let read = |p: &str| std::fs::read_to_string(format!("{root}/{p}")).unwrap();
        for (file, kind) in [
            ("configs/axiscomp.toml", FileKind::Service),
            ("configs/twin-service.toml", FileKind::Service),
            ("configs/sim.toml", FileKind::Twin),
            ("configs/optics/reference.toml", FileKind::Layout),
            ("plc-maps/io/generic.toml", FileKind::IoMap),
            ("plc-maps/io/wago-750-352-750-456.toml", FileKind::IoMap),
            ("plc-maps/cnc/generic.toml", FileKind::CncMap),
            ("plc-maps/cnc/siemens-s7-1500.toml", FileKind::CncMap),
        ] {
            assert_eq!(detect(&read(file)), Some(kind), "{file}");
        }
        assert_eq!(detect("[io\n"), None);
    }
}
