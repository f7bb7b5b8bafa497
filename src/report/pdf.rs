//! A small PDF 1.4 writer: pages of uncompressed content streams drawn with the base-14
//! fonts Helvetica and Helvetica-Bold in WinAnsiEncoding (so µ ° ± · × are available), vector
//! paths for charts, an Info dictionary and a cross-reference table with exact byte offsets.
//! Nothing is embedded and nothing outside this crate is called: every PDF reader has these
//! fonts. Characters WinAnsi lacks are written as words (↑ "up", ↓ "down") or their nearest
//! ASCII form (− "-", ≤ "<=").

use std::fmt::Write as _;

/// A4 portrait, in points.
pub const PAGE_W: f64 = 595.276;
pub const PAGE_H: f64 = 841.89;

/// The two fonts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Font {
    Regular,
    Bold,
}

impl Font {
    fn resource(self) -> &'static str {
        match self {
            Font::Regular => "F1",
            Font::Bold => "F2",
        }
    }
}

/// Text as WinAnsi bytes: Latin-1 is WinAnsi above 0xA0; a few typographic characters have
/// their own codes; arrows and signs WinAnsi lacks become words or ASCII.
pub fn winansi(s: &str) -> Vec<u8> {
    let mut out: Vec<u8> = Vec::with_capacity(s.len());
    // An arrow becomes a word, set off by a space after a letter or digit ("A↑" "A up").
    let word = |out: &mut Vec<u8>, w: &[u8]| {
        if out.last().is_some_and(u8::is_ascii_alphanumeric) {
            out.push(b' ');
        }
        out.extend_from_slice(w);
    };
    let mut chars = s.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '↑' => word(&mut out, b"up"),
            '↓' => word(&mut out, b"down"),
            // "√n" reads "sqrt n", "√(2/N)" "sqrt(2/N)".
            '√' if chars.peek().is_some_and(|n| n.is_alphanumeric()) => word(&mut out, b"sqrt "),
            '√' => word(&mut out, b"sqrt"),
            // The Greek letters of the uncertainty budget's formulas, as words.
            'Σ' => word(&mut out, b"sum"),
            'Δ' => word(&mut out, b"delta "),
            'α' => word(&mut out, b"alpha"),
            'β' => word(&mut out, b"beta"),
            'φ' => word(&mut out, b"phi"),
            'ρ' => word(&mut out, b"rho"),
            'σ' => word(&mut out, b"sigma"),
            'μ' => out.push(0xB5),
            '−' => out.push(b'-'),
            '≤' => out.extend_from_slice(b"<="),
            '≥' => out.extend_from_slice(b">="),
            '″' => out.push(b'"'),
            '′' => out.push(b'\''),
            '\u{0304}' => {} // a combining macron (B̄): the letter stays
            '–' => out.push(0x96),
            '—' => out.push(0x97),
            '…' => out.push(0x85),
            '•' => out.push(0x95),
            '‘' => out.push(0x91),
            '’' => out.push(0x92),
            '“' => out.push(0x93),
            '”' => out.push(0x94),
            '€' => out.push(0x80),
            c if (0x20..0x7F).contains(&(c as u32)) => out.push(c as u8),
            c if (0xA0..=0xFF).contains(&(c as u32)) => out.push(c as u32 as u8),
            '\t' | '\n' | '\r' => out.push(b' '),
            _ => out.push(b'?'),
        }
    }
    out
}

/// Helvetica advance widths (1/1000 em) of WinAnsi codes 32..=126.
const REGULAR: [u16; 95] = [
    278, 278, 355, 556, 556, 889, 667, 191, 333, 333, 389, 584, 278, 333, 278, 278, // sp ../
    556, 556, 556, 556, 556, 556, 556, 556, 556, 556, 278, 278, 584, 584, 584, 556, // 0..?
    1015, 667, 667, 722, 722, 667, 611, 778, 722, 278, 500, 667, 556, 833, 722, 778, // @..O
    667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611, 278, 278, 278, 469, 556, // P.._
    333, 556, 556, 500, 556, 556, 278, 556, 556, 222, 222, 500, 222, 833, 556, 556, // `..o
    556, 556, 333, 500, 278, 556, 500, 722, 500, 500, 500, 334, 260, 334, 584, // p..~
];

/// Helvetica-Bold advance widths (1/1000 em) of WinAnsi codes 32..=126.
const BOLD: [u16; 95] = [
    278, 333, 474, 556, 556, 889, 722, 238, 333, 333, 389, 584, 278, 333, 278, 278, //
    556, 556, 556, 556, 556, 556, 556, 556, 556, 556, 333, 333, 584, 584, 584, 611, //
    975, 722, 722, 722, 722, 667, 611, 778, 722, 278, 556, 722, 611, 833, 722, 778, //
    667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611, 333, 278, 333, 584, 556, //
    333, 556, 611, 556, 611, 556, 333, 611, 611, 278, 278, 556, 278, 889, 611, 611, //
    611, 611, 389, 556, 333, 611, 556, 778, 556, 556, 500, 389, 280, 389, 584, //
];

fn code_width(b: u8, font: Font) -> u16 {
    match b {
        32..=126 => match font {
            Font::Regular => REGULAR[(b - 32) as usize],
            Font::Bold => BOLD[(b - 32) as usize],
        },
        0xB0 => 400,               // °
        0xB1 | 0xD7 => 584,        // ± ×
        0xB7 => 278,               // ·
        0xB2 | 0xB3 | 0xB9 => 333, // ² ³ ¹
        0x97 | 0x85 => 1000,       // — …
        0x95 => 350,               // •
        0x91 | 0x92 => 222,        // ‘ ’
        0x93 | 0x94 => 333,        // “ ”
        _ => 556,                  // µ, Latin letters, –, €
    }
}

/// The width of `s` in points at `size`.
pub fn text_width(s: &str, font: Font, size: f64) -> f64 {
    winansi(s)
        .iter()
        .map(|&b| f64::from(code_width(b, font)))
        .sum::<f64>()
        * size
        / 1000.0
}

/// A PDF literal string of WinAnsi bytes: ( ) \ escaped, bytes outside ASCII as octal.
fn literal(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() + 2);
    s.push('(');
    for &b in bytes {
        match b {
            b'(' | b')' | b'\\' => {
                s.push('\\');
                s.push(b as char);
            }
            0x20..=0x7E => s.push(b as char),
            _ => {
                let _ = write!(s, "\\{b:03o}");
            }
        }
    }
    s.push(')');
    s
}

/// A number for a content stream: at most 2 decimals, no exponent.
fn n(v: f64) -> String {
    let s = format!("{v:.2}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" || s.is_empty() {
        "0".into()
    } else {
        s.to_string()
    }
}

/// One page's drawing, in page coordinates with y measured **down from the top** (the layout's
/// convention); converted to PDF's bottom-up coordinates here.
#[derive(Clone, Debug, Default)]
pub struct Page {
    ops: String,
}

impl Page {
    /// Text with its baseline's left end at (x, y).
    pub fn text(&mut self, x: f64, y: f64, s: &str, font: Font, size: f64) {
        let _ = writeln!(
            self.ops,
            "BT /{} {} Tf {} {} Td {} Tj ET",
            font.resource(),
            n(size),
            n(x),
            n(PAGE_H - y),
            literal(&winansi(s))
        );
    }

    /// Text turned 90° counter-clockwise (reading upwards), its baseline's start at (x, y).
    pub fn text_up(&mut self, x: f64, y: f64, s: &str, font: Font, size: f64) {
        let _ = writeln!(
            self.ops,
            "BT /{} {} Tf 0 1 -1 0 {} {} Tm {} Tj ET",
            font.resource(),
            n(size),
            n(x),
            n(PAGE_H - y),
            literal(&winansi(s))
        );
    }

    /// Fill colour for text and shapes (0..255 RGB).
    pub fn fill(&mut self, (r, g, b): (u8, u8, u8)) {
        let _ = writeln!(
            self.ops,
            "{} {} {} rg",
            n(f64::from(r) / 255.0),
            n(f64::from(g) / 255.0),
            n(f64::from(b) / 255.0)
        );
    }

    /// Stroke colour, line width and dash.
    pub fn stroke_style(&mut self, (r, g, b): (u8, u8, u8), width: f64, dashed: bool) {
        let _ = writeln!(
            self.ops,
            "{} {} {} RG {} w {} 0 d",
            n(f64::from(r) / 255.0),
            n(f64::from(g) / 255.0),
            n(f64::from(b) / 255.0),
            n(width),
            if dashed { "[3 2]" } else { "[]" }
        );
    }

    /// An open polyline, stroked.
    pub fn polyline(&mut self, pts: &[(f64, f64)]) {
        let Some((first, rest)) = pts.split_first() else {
            return;
        };
        let _ = write!(self.ops, "{} {} m", n(first.0), n(PAGE_H - first.1));
        for p in rest {
            let _ = write!(self.ops, " {} {} l", n(p.0), n(PAGE_H - p.1));
        }
        self.ops.push_str(" S\n");
    }

    /// A rectangle (top-left corner, width, height), stroked or filled.
    pub fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, filled: bool) {
        let _ = writeln!(
            self.ops,
            "{} {} {} {} re {}",
            n(x),
            n(PAGE_H - y - h),
            n(w),
            n(h),
            if filled { "f" } else { "S" }
        );
    }

    /// Save and restore the graphics state around `f`, clipped to a rectangle.
    pub fn clipped(&mut self, x: f64, y: f64, w: f64, h: f64, f: impl FnOnce(&mut Page)) {
        let _ = writeln!(
            self.ops,
            "q {} {} {} {} re W n",
            n(x),
            n(PAGE_H - y - h),
            n(w),
            n(h)
        );
        f(self);
        self.ops.push_str("Q\n");
    }
}

/// The document's Info entries.
#[derive(Clone, Debug, Default)]
pub struct Info {
    pub title: String,
    pub subject: String,
    /// "D:YYYYMMDDHHmmSSZ".
    pub creation_date: String,
}

/// The file: header, catalog, pages, fonts, Info, cross-reference table and trailer.
pub fn write(pages: &[Page], info: &Info) -> Vec<u8> {
    // Objects: 1 catalog, 2 pages, 3 Helvetica, 4 Helvetica-Bold, 5 Info, then per page its
    // page object and its content stream.
    let mut objects: Vec<Vec<u8>> = Vec::new();
    let page_ids: Vec<usize> = (0..pages.len()).map(|i| 6 + 2 * i).collect();
    objects.push(b"<< /Type /Catalog /Pages 2 0 R >>".to_vec());
    let kids: Vec<String> = page_ids.iter().map(|i| format!("{i} 0 R")).collect();
    objects.push(
        format!(
            "<< /Type /Pages /Kids [{}] /Count {} >>",
            kids.join(" "),
            pages.len()
        )
        .into_bytes(),
    );
    for name in ["Helvetica", "Helvetica-Bold"] {
        objects.push(
            format!(
                "<< /Type /Font /Subtype /Type1 /BaseFont /{name} /Encoding /WinAnsiEncoding >>"
            )
            .into_bytes(),
        );
    }
    objects.push(
        format!(
            "<< /Title {} /Subject {} /Producer (axiscomp {}) /CreationDate {} >>",
            literal(&winansi(&info.title)),
            literal(&winansi(&info.subject)),
            env!("CARGO_PKG_VERSION"),
            literal(info.creation_date.as_bytes())
        )
        .into_bytes(),
    );
    for (page, &id) in pages.iter().zip(&page_ids) {
        objects.push(
            format!(
                "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {} {}] \
                 /Resources << /Font << /F1 3 0 R /F2 4 0 R >> >> /Contents {} 0 R >>",
                n(PAGE_W),
                n(PAGE_H),
                id + 1
            )
            .into_bytes(),
        );
        let mut stream = format!("<< /Length {} >>\nstream\n", page.ops.len()).into_bytes();
        stream.extend_from_slice(page.ops.as_bytes());
        stream.extend_from_slice(b"\nendstream");
        objects.push(stream);
    }

    let mut out: Vec<u8> = b"%PDF-1.4\n%\xE2\xE3\xCF\xD3\n".to_vec();
    let mut offsets = Vec::with_capacity(objects.len());
    for (i, body) in objects.iter().enumerate() {
        offsets.push(out.len());
        out.extend_from_slice(format!("{} 0 obj\n", i + 1).as_bytes());
        out.extend_from_slice(body);
        out.extend_from_slice(b"\nendobj\n");
    }
    let xref = out.len();
    let mut table = format!("xref\n0 {}\n0000000000 65535 f \n", objects.len() + 1);
    for o in &offsets {
        let _ = writeln!(table, "{o:010} 00000 n ");
    }
    let _ = write!(
        table,
        "trailer\n<< /Size {} /Root 1 0 R /Info 5 0 R >>\nstartxref\n{xref}\n%%EOF\n",
        objects.len() + 1
    );
    out.extend_from_slice(table.as_bytes());
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn winansi_maps_units_and_arrows() {
        assert_eq!(
            winansi("±2 µm at 20 °C"),
            b"\xB12 \xB5m at 20 \xB0C".to_vec()
        );
        assert_eq!(winansi("A↑"), b"A up".to_vec());
        assert_eq!(winansi("E↓ −3"), b"E down -3".to_vec());
        assert_eq!(winansi("(↑ first)"), b"(up first)".to_vec());
        assert_eq!(winansi("A  accuracy"), b"A  accuracy".to_vec());
        // The budget's formulas: no Greek letter becomes '?'.
        assert_eq!(
            winansi("u(α)·|ΔT|·L, √(Σ sd²), cos φ, s/√n"),
            b"u(alpha)\xB7|delta T|\xB7L, sqrt(sum sd\xB2), cos phi, s/sqrt n".to_vec()
        );
        assert_eq!(literal(b"a(b)\\\xB5"), "(a\\(b\\)\\\\\\265)");
    }

    #[test]
    fn widths_are_helveticas() {
        // "Hello" in Helvetica: H 722 + e 556 + l 222 + l 222 + o 556 = 2278.
        assert!((text_width("Hello", Font::Regular, 10.0) - 22.78).abs() < 1e-9);
        assert!((text_width("10", Font::Bold, 1000.0) - 1112.0).abs() < 1e-9);
    }

    #[test]
    fn xref_offsets_point_at_their_objects() {
        let mut p = Page::default();
        p.text(50.0, 60.0, "E = 3.2 µm", Font::Regular, 10.0);
        let pdf = write(&[p.clone(), p], &Info::default());
        let text = String::from_utf8_lossy(&pdf);
        let start: usize = text
            .rsplit("startxref\n")
            .next()
            .and_then(|t| t.lines().next())
            .and_then(|l| l.parse().ok())
            .unwrap();
        assert!(pdf[start..].starts_with(b"xref\n0 10\n"));
        let xref = String::from_utf8_lossy(&pdf[start..]).into_owned();
        let entries: Vec<&str> = xref.lines().skip(3).take(9).collect();
        for (i, e) in entries.iter().enumerate() {
            let off: usize = e[..10].parse().unwrap();
            assert!(
                pdf[off..].starts_with(format!("{} 0 obj\n", i + 1).as_bytes()),
                "object {}",
                i + 1
            );
            assert_eq!(e.len(), 19, "an entry is 20 bytes with its newline");
        }
    }
}
