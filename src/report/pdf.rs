//! PDF pages, written by the `krilla` crate as archival PDF/A-2b (PDF 1.7): the built-in DejaVu
//! Sans and DejaVu Sans Bold embedded and subsetted (only the glyphs used), so every character
//! the report prints — µ σ √ Σ ″ ° ± · × ↑ ↓ − ≤ ≥ and the Greek of the budget's formulas — is
//! shown as itself and reads back as itself (each font carries its ToUnicode map). XMP metadata
//! (title, subject, creator, language, creation date) and an sRGB output intent come with the
//! PDF/A conformance; krilla's PDF/A-2b check runs on every file and a file that fails it is
//! not written.
//!
//! A [`Page`] records drawing operations in the layout's coordinates (points, origin top-left, y
//! measured **down** from the top, as krilla's pages are); [`write`] replays them onto krilla's
//! page surfaces. Text is shaped once (rustybuzz: the font's advance widths, kerning, ligatures,
//! a combining mark over its letter) and placed glyph by glyph as shaped; [`text_width`] sums the
//! same shaping's advances, so a right-aligned number ends where the layout measured it.

use krilla::Document;
use krilla::color::rgb;
use krilla::configure::{Archival, ConfigurationBuilder, PdfVersion, ValidationError};
use krilla::error::KrillaError;
use krilla::geom::{Path, PathBuilder, Point, Rect, Transform};
use krilla::metadata::{DateTime, Metadata};
use krilla::num::NormalizedF32;
use krilla::page::PageSettings;
use krilla::paint::{Fill, FillRule, Stroke, StrokeDash};
use krilla::surface::Surface;
use krilla::text::{GlyphId, KrillaGlyph};
use krilla::{Data, SerializeSettings};
use std::sync::LazyLock;
use thiserror::Error;

/// A4 portrait, in points.
pub const PAGE_W: f64 = 595.276;
pub const PAGE_H: f64 = 841.89;

/// DejaVu Sans 2.37 (Bitstream Vera licence, `fonts/LICENSE-DejaVu.txt`): the binary carries
/// the fonts, a machine needs none installed.
const REGULAR_TTF: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");
const BOLD_TTF: &[u8] = include_bytes!("fonts/DejaVuSans-Bold.ttf");

/// The two fonts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Font {
    Regular,
    Bold,
}

impl Font {
    fn name(self) -> &'static str {
        match self {
            Font::Regular => "DejaVu Sans",
            Font::Bold => "DejaVu Sans Bold",
        }
    }
}

/// Why a PDF could not be written.
#[derive(Debug, Error)]
pub enum PdfError {
    #[error("the built-in PDF font {0} could not be read; this build is broken")]
    Font(&'static str),
    #[error(
        "the PDF's creation date \"{0}\" is not of the form D:YYYYMMDDHHmmSSZ (a date from 1970 on, \
         in UTC)"
    )]
    Date(String),
    #[error("the PDF fails the PDF/A-2b check, so it was not written: {0}")]
    NotArchival(String),
    #[error("the PDF could not be written: {0}")]
    Krilla(String),
}

/// One font, parsed once: krilla's handle (what the PDF embeds) and rustybuzz's (the shaper:
/// the glyphs, their advances with the font's kerning, and combining marks such as the macron
/// of B̄ placed over their base by the font's mark positioning). The layout measures text and
/// the page shows it from one shaping, so the two cannot disagree.
struct Face {
    pdf: krilla::text::Font,
    shaper: rustybuzz::Face<'static>,
    units_per_em: f32,
}

impl Face {
    fn parse(data: &'static [u8]) -> Option<Face> {
        let shaper = rustybuzz::Face::from_slice(data, 0)?;
        // '?' stands in for characters the font lacks: it must have it.
        shaper.glyph_index('?')?;
        Some(Face {
            pdf: krilla::text::Font::new(Data::from(data), 0)?,
            units_per_em: shaper.units_per_em() as f32,
            shaper,
        })
    }

    /// Whether the font has a glyph of its own for `c`.
    fn has(&self, c: char) -> bool {
        self.shaper.glyph_index(c).is_some_and(|g| g.0 != 0)
    }

    /// The text as it is shown — a tab or line end as a space, a character the font lacks as
    /// '?' (PDF/A refuses the .notdef glyph) — and its glyphs, shaped left to right, each with
    /// its advance and offsets (ems) and the bytes of the shown text it stands for.
    fn glyphs(&self, s: &str) -> (String, Vec<KrillaGlyph>) {
        let shown: String = s
            .chars()
            .map(|c| match c {
                c if c.is_control() => ' ',
                c if self.has(c) => c,
                _ => '?',
            })
            .collect();
        if shown.is_empty() {
            return (shown, Vec::new());
        }
        let mut buffer = rustybuzz::UnicodeBuffer::new();
        buffer.push_str(&shown);
        buffer.guess_segment_properties();
        buffer.set_direction(rustybuzz::Direction::LeftToRight);
        let out = rustybuzz::shape(&self.shaper, &[], buffer);
        let (infos, positions) = (out.glyph_infos(), out.glyph_positions());
        let em = |v: i32| v as f32 / self.units_per_em;
        let glyphs = infos
            .iter()
            .zip(positions)
            .enumerate()
            .map(|(i, (info, pos))| {
                // A cluster (a base and its marks) ends where the next one starts.
                let start = info.cluster as usize;
                let end = infos[i + 1..]
                    .iter()
                    .map(|n| n.cluster as usize)
                    .find(|&c| c != start)
                    .unwrap_or(shown.len());
                KrillaGlyph::new(
                    GlyphId::new(info.glyph_id),
                    em(pos.x_advance),
                    em(pos.x_offset),
                    em(pos.y_offset),
                    em(pos.y_advance),
                    start..end,
                    None,
                )
            })
            .collect();
        (shown, glyphs)
    }
}

static REGULAR: LazyLock<Option<Face>> = LazyLock::new(|| Face::parse(REGULAR_TTF));
static BOLD: LazyLock<Option<Face>> = LazyLock::new(|| Face::parse(BOLD_TTF));

fn face(font: Font) -> Result<&'static Face, PdfError> {
    let face = match font {
        Font::Regular => &*REGULAR,
        Font::Bold => &*BOLD,
    };
    face.as_ref().ok_or(PdfError::Font(font.name()))
}

/// The text as the PDF shows it, for a canvas that draws glyph outlines itself (`raster`):
/// the font's face and the glyphs with their advances and offsets (ems), from the same
/// shaping. `None` when the built-in font cannot be parsed (a broken build).
pub(super) fn shaped(
    s: &str,
    font: Font,
) -> Option<(&'static rustybuzz::Face<'static>, Vec<KrillaGlyph>)> {
    let f = face(font).ok()?;
    Some((&f.shaper, f.glyphs(s).1))
}

/// The width of `s` in points at `size`: the advances of the glyphs the PDF shows for it, as
/// shaped (the font's advance widths, with its kerning).
pub fn text_width(s: &str, font: Font, size: f64) -> f64 {
    match face(font) {
        Ok(f) => {
            let (_, glyphs) = f.glyphs(s);
            glyphs.iter().map(|g| f64::from(g.x_advance)).sum::<f64>() * size
        }
        // A broken build: `write` refuses to write; measure something plausible meanwhile.
        Err(_) => s.chars().count() as f64 * 0.6 * size,
    }
}

/// One drawing operation of a page.
#[derive(Clone, Debug, PartialEq)]
enum Op {
    Text {
        x: f64,
        y: f64,
        text: String,
        font: Font,
        size: f64,
        /// Turned 90° counter-clockwise about (x, y), reading upwards.
        up: bool,
    },
    Fill((u8, u8, u8)),
    Stroke {
        rgb: (u8, u8, u8),
        width: f64,
        dashed: bool,
    },
    Polyline(Vec<(f64, f64)>),
    Rect {
        x: f64,
        y: f64,
        w: f64,
        h: f64,
        filled: bool,
    },
    Circle {
        x: f64,
        y: f64,
        r: f64,
        filled: bool,
    },
    /// A closed polygon filled with a colour at an opacity, not stroked.
    Polygon {
        pts: Vec<(f64, f64)>,
        rgb: (u8, u8, u8),
        opacity: f64,
    },
    /// Operations clipped to a rectangle; colours and line style set inside end with it.
    Clipped {
        x: f64,
        y: f64,
        w: f64,
        h: f64,
        ops: Vec<Op>,
    },
}

/// One page's drawing, in page coordinates (points) with y measured **down from the top**.
/// Colours and the line style hold until set again (initially black, 1 pt, solid).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Page {
    ops: Vec<Op>,
}

impl Page {
    /// Text with its baseline's left end at (x, y).
    pub fn text(&mut self, x: f64, y: f64, s: &str, font: Font, size: f64) {
        self.ops.push(Op::Text {
            x,
            y,
            text: s.to_string(),
            font,
            size,
            up: false,
        });
    }

    /// Text turned 90° counter-clockwise (reading upwards), its baseline's start at (x, y).
    pub fn text_up(&mut self, x: f64, y: f64, s: &str, font: Font, size: f64) {
        self.ops.push(Op::Text {
            x,
            y,
            text: s.to_string(),
            font,
            size,
            up: true,
        });
    }

    /// Fill colour for text and shapes (0..255 RGB).
    pub fn fill(&mut self, rgb: (u8, u8, u8)) {
        self.ops.push(Op::Fill(rgb));
    }

    /// Stroke colour, line width and dash.
    pub fn stroke_style(&mut self, rgb: (u8, u8, u8), width: f64, dashed: bool) {
        self.ops.push(Op::Stroke { rgb, width, dashed });
    }

    /// An open polyline, stroked.
    pub fn polyline(&mut self, pts: &[(f64, f64)]) {
        if pts.len() >= 2 {
            self.ops.push(Op::Polyline(pts.to_vec()));
        }
    }

    /// A rectangle (top-left corner, width, height), stroked or filled.
    pub fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, filled: bool) {
        self.ops.push(Op::Rect { x, y, w, h, filled });
    }

    /// A circle (centre, radius), stroked or filled.
    pub fn circle(&mut self, x: f64, y: f64, r: f64, filled: bool) {
        self.ops.push(Op::Circle { x, y, r, filled });
    }

    /// A closed polygon filled with `rgb` at `opacity` (0 to 1; PDF/A-2 allows transparency).
    pub fn polygon(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64) {
        if pts.len() >= 3 {
            self.ops.push(Op::Polygon {
                pts: pts.to_vec(),
                rgb,
                opacity,
            });
        }
    }

    /// What `f` draws, clipped to a rectangle; colours and line style it sets end with it.
    pub fn clipped(&mut self, x: f64, y: f64, w: f64, h: f64, f: impl FnOnce(&mut Page)) {
        let mut inner = Page::default();
        f(&mut inner);
        self.ops.push(Op::Clipped {
            x,
            y,
            w,
            h,
            ops: inner.ops,
        });
    }
}

/// The document's metadata.
#[derive(Clone, Debug, Default)]
pub struct Info {
    pub title: String,
    pub subject: String,
    /// "D:YYYYMMDDHHmmSSZ" (UTC).
    pub creation_date: String,
}

/// "D:YYYYMMDDHHmmSSZ" as krilla's date.
fn date(s: &str) -> Result<DateTime, PdfError> {
    let bad = || PdfError::Date(s.to_string());
    let digits = s
        .strip_prefix("D:")
        .and_then(|t| t.strip_suffix('Z'))
        .filter(|t| t.len() == 14 && t.bytes().all(|b| b.is_ascii_digit()))
        .ok_or_else(bad)?;
    let num = |r: std::ops::Range<usize>| digits[r].parse::<u16>().map_err(|_| bad());
    let (year, month, day) = (num(0..4)?, num(4..6)?, num(6..8)?);
    let (hour, minute, second) = (num(8..10)?, num(10..12)?, num(12..14)?);
    let ok = (1970..=9999).contains(&year)
        && (1..=12).contains(&month)
        && (1..=31).contains(&day)
        && hour < 24
        && minute < 60
        && second < 60;
    if !ok {
        return Err(bad());
    }
    // Every value is checked to fit a u8 above.
    let b = |v: u16| u8::try_from(v).unwrap_or(0);
    Ok(DateTime::new(year)
        .month(b(month))
        .day(b(day))
        .hour(b(hour))
        .minute(b(minute))
        .second(b(second))
        .utc_offset_hour(0)
        .utc_offset_minute(0))
}

fn colour((r, g, b): (u8, u8, u8)) -> rgb::Color {
    rgb::Color::new(r, g, b)
}

fn fill_of(rgb: (u8, u8, u8)) -> Fill {
    Fill {
        paint: colour(rgb).into(),
        opacity: NormalizedF32::ONE,
        rule: FillRule::NonZero,
    }
}

fn point(x: f64, y: f64) -> Point {
    Point::from_xy(x as f32, y as f32)
}

fn polyline_path(pts: &[(f64, f64)]) -> Option<Path> {
    let (first, rest) = pts.split_first()?;
    let mut pb = PathBuilder::new();
    pb.move_to(first.0 as f32, first.1 as f32);
    for p in rest {
        pb.line_to(p.0 as f32, p.1 as f32);
    }
    pb.finish()
}

fn rect_path(x: f64, y: f64, w: f64, h: f64) -> Option<Path> {
    let mut pb = PathBuilder::new();
    pb.push_rect(Rect::from_xywh(x as f32, y as f32, w as f32, h as f32)?);
    pb.finish()
}

/// A circle as four cubic Béziers (the usual 0.5523 handle: within 0.03 % of the radius).
fn circle_path(x: f64, y: f64, r: f64) -> Option<Path> {
    let (x, y, r) = (x as f32, y as f32, r as f32);
    let k = 0.552_284_8 * r;
    let mut pb = PathBuilder::new();
    pb.move_to(x + r, y);
    pb.cubic_to(x + r, y + k, x + k, y + r, x, y + r);
    pb.cubic_to(x - k, y + r, x - r, y + k, x - r, y);
    pb.cubic_to(x - r, y - k, x - k, y - r, x, y - r);
    pb.cubic_to(x + k, y - r, x + r, y - k, x + r, y);
    pb.close();
    pb.finish()
}

/// The graphics state a page's operations set.
#[derive(Clone)]
struct State {
    fill: (u8, u8, u8),
    stroke: Stroke,
}

impl Default for State {
    fn default() -> State {
        State {
            fill: (0, 0, 0),
            stroke: Stroke {
                paint: colour((0, 0, 0)).into(),
                width: 1.0,
                ..Stroke::default()
            },
        }
    }
}

/// A closed shape, filled with the fill colour or stroked with the line style.
fn shape(surface: &mut Surface, state: &State, path: Option<Path>, filled: bool) {
    let Some(path) = path else {
        return;
    };
    if filled {
        surface.set_stroke(None);
        surface.set_fill(Some(fill_of(state.fill)));
    } else {
        surface.set_fill(None);
        surface.set_stroke(Some(state.stroke.clone()));
    }
    surface.draw_path(&path);
}

fn replay(surface: &mut Surface, ops: &[Op], state: &mut State) -> Result<(), PdfError> {
    for op in ops {
        match op {
            Op::Fill(rgb) => state.fill = *rgb,
            Op::Stroke { rgb, width, dashed } => {
                state.stroke = Stroke {
                    paint: colour(*rgb).into(),
                    width: *width as f32,
                    dash: dashed.then(|| StrokeDash {
                        array: vec![3.0, 2.0],
                        offset: 0.0,
                    }),
                    ..Stroke::default()
                };
            }
            Op::Polyline(pts) => {
                if let Some(path) = polyline_path(pts) {
                    surface.set_fill(None);
                    surface.set_stroke(Some(state.stroke.clone()));
                    surface.draw_path(&path);
                }
            }
            Op::Rect { x, y, w, h, filled } => {
                shape(surface, state, rect_path(*x, *y, *w, *h), *filled);
            }
            Op::Circle { x, y, r, filled } => {
                shape(surface, state, circle_path(*x, *y, *r), *filled);
            }
            Op::Polygon { pts, rgb, opacity } => {
                let mut closed = pts.clone();
                closed.extend(pts.first().copied());
                if let Some(path) = polyline_path(&closed) {
                    surface.set_stroke(None);
                    surface.set_fill(Some(Fill {
                        opacity: NormalizedF32::new(opacity.clamp(0.0, 1.0) as f32)
                            .unwrap_or(NormalizedF32::ONE),
                        ..fill_of(*rgb)
                    }));
                    surface.draw_path(&path);
                }
            }
            Op::Text {
                x,
                y,
                text,
                font,
                size,
                up,
            } => {
                let face = face(*font)?;
                let (shown, glyphs) = face.glyphs(text);
                if glyphs.is_empty() {
                    continue;
                }
                surface.set_stroke(None);
                surface.set_fill(Some(fill_of(state.fill)));
                if *up {
                    surface.push_transform(&Transform::from_rotate_at(-90.0, *x as f32, *y as f32));
                }
                surface.draw_glyphs(
                    point(*x, *y),
                    &glyphs,
                    face.pdf.clone(),
                    &shown,
                    *size as f32,
                    false,
                );
                if *up {
                    surface.pop();
                }
            }
            Op::Clipped { x, y, w, h, ops } => {
                // A clip of no area shows nothing.
                if let Some(path) = rect_path(*x, *y, *w, *h) {
                    surface.push_clip_path(&path, &FillRule::NonZero);
                    let mut inner = state.clone();
                    let drawn = replay(surface, ops, &mut inner);
                    surface.pop();
                    drawn?;
                }
            }
        }
    }
    Ok(())
}

/// What a validation error says, in words.
fn validation_error(e: &ValidationError) -> String {
    match e {
        ValidationError::ContainsNotDefGlyph(_, _, text) => {
            format!("a character the font lacks, in \"{text}\"")
        }
        ValidationError::NoDocumentTitle => "no title".into(),
        ValidationError::NoDocumentLanguage => "no language".into(),
        ValidationError::MissingDocumentDate => "no creation date".into(),
        ValidationError::Transparency(_) => "transparency".into(),
        // The rule by krilla's own name for it: the last resort for a rule not worded here.
        other => format!("the rule krilla names {other:?}"),
    }
}

fn krilla_error(e: KrillaError) -> PdfError {
    match e {
        KrillaError::Validation(errors) => {
            let mut said: Vec<String> = errors.iter().map(|(e, _)| validation_error(e)).collect();
            said.dedup();
            PdfError::NotArchival(said.join("; "))
        }
        other => PdfError::Krilla(other.to_string()),
    }
}

/// The file: PDF/A-2b (PDF 1.7), one A4 page per `pages` entry, `info` as its metadata with
/// the language "en", creator and producer this program.
pub fn write(pages: &[Page], info: &Info) -> Result<Vec<u8>, PdfError> {
    let configuration = ConfigurationBuilder::new()
        .with_version(PdfVersion::Pdf17)
        .with_archival_validator(Archival::A2_B)
        .finish()
        .map_err(|e| PdfError::Krilla(format!("its settings are refused: {e:?}")))?;
    let settings = SerializeSettings {
        configuration,
        // The report is not tagged: PDF/A-2b does not ask for a structure tree (2a would).
        enable_tagging: false,
        ..SerializeSettings::default()
    };
    let mut document = Document::new_with(settings);
    let program = format!("axiscomp {}", env!("CARGO_PKG_VERSION"));
    document.set_metadata(
        Metadata::new()
            .title(info.title.clone())
            .description(info.subject.clone())
            .creator(program.clone())
            .producer(format!("{program} (krilla 0.8)"))
            .language("en".into())
            .creation_date(date(&info.creation_date)?),
    );
    let size = PageSettings::from_wh(PAGE_W as f32, PAGE_H as f32)
        .ok_or_else(|| PdfError::Krilla("the A4 page size was refused".into()))?;
    for p in pages {
        let mut page = document.start_page_with(size.clone());
        let mut surface = page.surface();
        replay(&mut surface, &p.ops, &mut State::default())?;
        surface.finish();
        page.finish();
    }
    document.finish().map_err(krilla_error)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info() -> Info {
        Info {
            title: "Acceptance µ test".into(),
            subject: "Axis X".into(),
            creation_date: "D:20250102030405Z".into(),
        }
    }

    /// Whether `font` has a glyph of its own for `c` (else the PDF shows '?').
    fn has_glyph(c: char, font: Font) -> bool {
        face(font).is_ok_and(|f| f.has(c))
    }

    fn find(hay: &[u8], needle: &[u8]) -> bool {
        hay.windows(needle.len()).any(|w| w == needle)
    }

    #[test]
    fn a_pdf_a_2b_file_of_pdf_1_7() {
        let mut p = Page::default();
        p.text(50.0, 60.0, "E = 3.2 µm", Font::Regular, 10.0);
        p.text_up(40.0, 300.0, "dz (µm)", Font::Bold, 7.0);
        p.stroke_style((200, 0, 0), 0.6, true);
        p.polyline(&[(50.0, 100.0), (200.0, 150.0)]);
        p.clipped(50.0, 100.0, 100.0, 50.0, |p| {
            p.fill((0, 0, 255));
            p.rect(60.0, 110.0, 3.2, 3.2, true);
        });
        let pdf = write(&[p.clone(), p], &info()).expect("pdf");
        assert!(pdf.starts_with(b"%PDF-1.7\n"), "header");
        // PDF/A: a comment of bytes above 127 on the second line.
        assert!(pdf[9] == b'%' && pdf[10..14].iter().all(|&b| b > 127));
        assert!(pdf.ends_with(b"%%EOF\n") || pdf.ends_with(b"%%EOF"));
        // The XMP packet (not compressed) names the conformance and the metadata.
        for needle in [
            &b"<pdfaid:part>2</pdfaid:part>"[..],
            b"<pdfaid:conformance>B</pdfaid:conformance>",
            b"Acceptance \xC2\xB5 test",
            b"axiscomp ",
            b"2025-01-02T03:04:05",
            b"/OutputIntents",
        ] {
            assert!(find(&pdf, needle), "{}", String::from_utf8_lossy(needle));
        }
        // Two subsetted CID fonts with their programs embedded, nothing of the base 14.
        assert!(find(&pdf, b"/FontFile2"), "TrueType programs embedded");
        assert!(find(&pdf, b"+DejaVuSans/"), "DejaVu Sans subset");
        assert!(find(&pdf, b"+DejaVuSans-Bold"), "DejaVu Sans Bold subset");
        assert!(!find(&pdf, b"Helvetica") && !find(&pdf, b"WinAnsiEncoding"));
    }

    #[test]
    fn a_bad_creation_date_is_an_error_not_a_file() {
        for bad in ["", "D:2025010203040Z", "2025-01-02", "D:20251302030405Z"] {
            let e = write(
                &[Page::default()],
                &Info {
                    creation_date: bad.into(),
                    ..info()
                },
            );
            assert!(
                matches!(&e, Err(PdfError::Date(d)) if d == bad),
                "{bad}: {e:?}"
            );
        }
        assert!(date("D:19700101000000Z").is_ok());
    }

    #[test]
    fn widths_are_dejavu_sans_advances() {
        use skrifa::instance::{LocationRef, Size};
        use skrifa::{FontRef, MetadataProvider};
        // DejaVu Sans: 2048 units per em; W advances 2025 units, Bold's W 2259 (read from the
        // fonts' hmtx by hand, and here by skrifa, independently of the shaper).
        for (data, font, w_units) in [
            (REGULAR_TTF, Font::Regular, 2025.0),
            (BOLD_TTF, Font::Bold, 2259.0),
        ] {
            let f = FontRef::new(data).expect("skrifa reads it");
            let upem = f
                .metrics(Size::unscaled(), LocationRef::default())
                .units_per_em;
            assert_eq!(upem, 2048);
            let metrics = f.glyph_metrics(Size::unscaled(), LocationRef::default());
            let adv = |c: char| {
                let g = f.charmap().map(c).expect("glyph");
                f64::from(metrics.advance_width(g).expect("advance"))
            };
            assert_eq!(adv('W'), w_units);
            let w = text_width("W", font, 10.0);
            assert!((w - w_units / 2048.0 * 10.0).abs() < 1e-4, "{w}");
            // Figures and units: no kerning, the advances' sum.
            let s = "µ σ √ Σ ″ ↑ −3.08 µm ± 0.1″";
            let expected: f64 = s.chars().map(adv).sum::<f64>() / 2048.0 * 9.0;
            assert!((text_width(s, font, 9.0) - expected).abs() < 1e-3, "{s}");
            // A kerned pair is measured as shown: closer than its advances.
            let av = (adv('A') + adv('V')) / 2048.0 * 10.0;
            assert!(text_width("AV", font, 10.0) < av - 0.1, "DejaVu kerns A V");
        }
    }

    #[test]
    fn a_combining_mark_sits_over_its_letter() {
        // B̄ (the mean reversal value): the macron adds no width and is raised over the capital
        // by the font's mark positioning (unshaped, it would cut through the B's top).
        let f = face(Font::Regular).expect("font");
        let (shown, glyphs) = f.glyphs("B\u{304}");
        assert_eq!(shown, "B\u{304}");
        assert_eq!(glyphs.len(), 2);
        assert_eq!(glyphs[1].x_advance, 0.0);
        assert!(glyphs[1].y_offset > 0.1, "{:?}", glyphs[1]);
        assert_eq!(glyphs[0].text_range, 0..3, "one cluster");
        assert_eq!(
            text_width("B\u{304} mean", Font::Regular, 10.0),
            text_width("B mean", Font::Regular, 10.0)
        );
    }

    #[test]
    fn the_reports_characters_have_glyphs_of_their_own() {
        // Every non-ASCII character the report's text producers use (acceptance, budget,
        // units, text): none becomes '?'.
        let s = "µμσ√Σ″′°±·×↑↓−≤≥≈→…–—αβφρΔ∂²³¹⁻ᵀ§éūB\u{304}";
        for font in [Font::Regular, Font::Bold] {
            for c in s.chars() {
                assert!(has_glyph(c, font), "{c:?} ({:04X}) in {font:?}", c as u32);
            }
        }
        // One the font lacks is shown and measured as '?' (PDF/A refuses .notdef).
        assert!(!has_glyph('中', Font::Regular));
        assert_eq!(
            text_width("a中", Font::Regular, 10.0),
            text_width("a?", Font::Regular, 10.0)
        );
        let mut p = Page::default();
        p.text(50.0, 60.0, "x 中\t", Font::Regular, 10.0);
        assert!(write(&[p], &info()).is_ok());
    }

    /// The page's content stream, inflated.
    fn content(pdf: &[u8]) -> String {
        let mut found = Vec::new();
        let mut rest = pdf;
        while let Some(i) = rest.windows(8).position(|w| w == b"\nstream\n") {
            let dict_start = rest[..i].windows(2).rposition(|w| w == b"<<").unwrap_or(0);
            let dict = String::from_utf8_lossy(&rest[dict_start..i]).into_owned();
            let len: usize = dict
                .split("/Length ")
                .nth(1)
                .and_then(|t| t.split(|c: char| !c.is_ascii_digit()).next())
                .and_then(|t| t.parse().ok())
                .expect("length");
            let data = &rest[i + 8..i + 8 + len];
            let mut text = Vec::new();
            if dict.contains("/FlateDecode")
                && std::io::Read::read_to_end(&mut flate2::read::ZlibDecoder::new(data), &mut text)
                    .is_ok()
                && text.starts_with(b"q ")
            {
                found.push(String::from_utf8_lossy(&text).into_owned());
            }
            rest = &rest[i + 8 + len..];
        }
        assert_eq!(found.len(), 1, "one page");
        found.remove(0)
    }

    #[test]
    fn a_clip_keeps_its_colours_and_text_up_turns() {
        let mut p = Page::default();
        p.fill((255, 0, 0));
        p.clipped(10.0, 20.0, 100.0, 50.0, |p| {
            p.fill((0, 0, 255));
            p.rect(30.0, 40.0, 5.0, 5.0, true);
        });
        p.rect(200.0, 300.0, 5.0, 5.0, true);
        p.text_up(40.0, 400.0, "up", Font::Regular, 9.0);
        let c = content(&write(&[p], &info()).expect("pdf"));
        // The clip rectangle, turned to PDF's bottom-up coordinates (841.89 − 20, − 70).
        let clip = c
            .find("10 821.89 m 110 821.89 l 110 771.89 l 10 771.89 l\nh\nW\nn")
            .expect("the clip");
        // Blue inside the clip's saved state, red after it is restored: count q and Q.
        let depth = |end: usize| {
            let t: Vec<&str> = c[..end].split_whitespace().collect();
            t.iter().filter(|t| **t == "q").count() as i64
                - t.iter().filter(|t| **t == "Q").count() as i64
        };
        let blue = c.find("0 0 1 scn").expect("blue");
        let red = c.find("1 0 0 scn").expect("red");
        assert!(clip < blue && blue < red, "{c}");
        assert_eq!((depth(blue), depth(red)), (2, 1), "{c}");
        // The turned text: text matrix × transformation is PDF's "0 1 −1 0 x (841.89 − y)", a
        // quarter turn counter-clockwise about its start (what the old writer's Tm said).
        let nums = |op: &str| -> Vec<f64> {
            let end = c.rfind(op).expect(op);
            let mut v: Vec<f64> = c[..end]
                .split(|ch: char| ch.is_whitespace() || ch == '/' || ch == ']')
                .rev()
                .take(6)
                .map(|t| t.parse().expect("a number"))
                .collect();
            v.reverse();
            v
        };
        let (t, m) = (nums(" Tm"), nums(" cm"));
        let product = [
            t[0] * m[0] + t[1] * m[2],
            t[0] * m[1] + t[1] * m[3],
            t[2] * m[0] + t[3] * m[2],
            t[2] * m[1] + t[3] * m[3],
            t[4] * m[0] + t[5] * m[2] + m[4],
            t[4] * m[1] + t[5] * m[3] + m[5],
        ];
        let want = [0.0, 1.0, -1.0, 0.0, 40.0, 841.89 - 400.0];
        for (got, want) in product.iter().zip(want) {
            assert!((got - want).abs() < 1e-3, "{product:?}\n{c}");
        }
    }

    #[test]
    fn the_same_pages_give_the_same_bytes() {
        let mut p = Page::default();
        p.text(50.0, 60.0, "E = 3.2 µm", Font::Regular, 10.0);
        let a = write(std::slice::from_ref(&p), &info()).expect("pdf");
        let b = write(&[p], &info()).expect("pdf");
        assert!(a == b, "a report written twice is the same file");
    }

    /// With poppler: a page with the report's symbols reads back as those symbols, from the
    /// embedded subset fonts.
    #[test]
    #[ignore = "needs poppler-utils (pdftotext, pdffonts); .ci/run installs them"]
    fn poppler_reads_the_symbols_back() {
        let dir = std::env::temp_dir().join(format!("axiscomp-pdf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("symbols.pdf");
        let line = "u = 0.5 µm, σ = √(Σ x²)/n, 2.0″ ↑ ↓ − ≤ ≥ ± · × 20 °C α ΔT";
        let bold = "Bold: σ √ Σ ″";
        let mut p = Page::default();
        p.text(50.0, 80.0, line, Font::Regular, 12.0);
        p.text(50.0, 100.0, bold, Font::Bold, 12.0);
        p.text_up(40.0, 400.0, "upwards µm", Font::Regular, 9.0);
        std::fs::write(&path, write(&[p], &info()).expect("pdf")).expect("write");
        let run = |cmd: &str, args: &[&str]| {
            let o = std::process::Command::new(cmd)
                .args(args)
                .arg(&path)
                .args(if cmd == "pdftotext" {
                    &["-"][..]
                } else {
                    &[][..]
                })
                .output()
                .unwrap_or_else(|e| panic!("{cmd} (apt-get install poppler-utils): {e}"));
            assert!(o.status.success(), "{cmd}");
            assert!(
                o.stderr.is_empty(),
                "{cmd}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            String::from_utf8(o.stdout).expect("utf-8")
        };
        let text = run("pdftotext", &["-enc", "UTF-8"]);
        // pdftotext keeps a space only where it can tell word spacing from letter spacing (it
        // joins "1 2 3" into "123" in any font): compare the characters, then the words.
        let squeeze = |s: &str| s.split_whitespace().collect::<String>();
        for l in [line, bold, "upwards µm"] {
            assert!(squeeze(&text).contains(&squeeze(l)), "{l:?} in {text}");
        }
        assert!(text.contains("u = 0.5 µm, σ = √(Σ x²)/n, 2.0″"), "{text}");
        let fonts = run("pdffonts", &[]);
        let rows: Vec<&str> = fonts.lines().skip(2).collect();
        assert_eq!(rows.len(), 2, "{fonts}");
        for r in rows {
            let f: Vec<&str> = r.split_whitespace().collect();
            // name, type (2 words), encoding, emb, sub, uni, object, generation
            assert!(f[0].len() > 7 && f[0].as_bytes()[6] == b'+', "subset: {r}");
            assert!(f[0].contains("DejaVuSans"), "{r}");
            assert_eq!(f[f.len() - 5..f.len() - 2], ["yes", "yes", "yes"], "{r}");
        }
        let info = run("pdfinfo", &[]);
        let field = |name: &str| {
            info.lines()
                .find_map(|l| l.strip_prefix(name))
                .map(str::trim)
                .unwrap_or_else(|| panic!("{name} in {info}"))
        };
        assert_eq!(field("PDF version:"), "1.7");
        assert_eq!(field("Title:"), "Acceptance µ test");
        assert_eq!(
            field("Creator:"),
            concat!("axiscomp ", env!("CARGO_PKG_VERSION"))
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
