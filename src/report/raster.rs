//! A chart canvas onto pixels, written as PNG (`tiny-skia`): the run report's PNG charts drawn
//! by the same code as its SVGs and the PDF's (`chart`). Text is the PDF's own shaping of the
//! built-in DejaVu Sans (`pdf::shaped`), its glyph outlines filled as paths, so a PNG shows
//! the same characters (µ, ″, ↑) at the same widths as the other two; anti-aliased, on white.

use super::chart::{Canvas, MARKER_R, TextStyle};
use super::pdf::{Font, shaped};
use tiny_skia::{
    Color, FillRule, LineCap, LineJoin, Paint, PathBuilder, Pixmap, Stroke, StrokeDash, Transform,
};

/// A picture being drawn, in points scaled by `scale` to pixels.
pub struct Raster {
    pixmap: Pixmap,
    scale: f32,
}

/// Why a picture could not be made.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    #[error("a picture of {w:.0} × {h:.0} points at {scale}× has no pixels or too many")]
    Size { w: f64, h: f64, scale: f64 },
    #[error("PNG encoding failed: {0}")]
    Png(String),
}

impl Raster {
    /// A white picture `w` × `h` points at `scale` pixels per point.
    pub fn new(w: f64, h: f64, scale: f64) -> Result<Raster, RasterError> {
        let size = RasterError::Size { w, h, scale };
        let px = |v: f64| {
            let p = (v * scale).ceil();
            (1.0..=16_384.0).contains(&p).then_some(p as u32)
        };
        let (Some(pw), Some(ph)) = (px(w), px(h)) else {
            return Err(size);
        };
        let mut pixmap = Pixmap::new(pw, ph).ok_or(size)?;
        pixmap.fill(Color::WHITE);
        Ok(Raster {
            pixmap,
            scale: scale as f32,
        })
    }

    /// The picture as PNG bytes.
    pub fn png(&self) -> Result<Vec<u8>, RasterError> {
        self.pixmap
            .encode_png()
            .map_err(|e| RasterError::Png(e.to_string()))
    }

    fn transform(&self) -> Transform {
        Transform::from_scale(self.scale, self.scale)
    }
}

fn paint((r, g, b): (u8, u8, u8), opacity: f64) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color_rgba8(r, g, b, (opacity.clamp(0.0, 1.0) * 255.0).round() as u8);
    p.anti_alias = true;
    p
}

fn stroke(width: f64, dashed: bool) -> Stroke {
    Stroke {
        width: width as f32,
        line_cap: LineCap::Butt,
        line_join: LineJoin::Round,
        dash: if dashed {
            StrokeDash::new(vec![3.0, 2.0], 0.0)
        } else {
            None
        },
        ..Stroke::default()
    }
}

fn polyline(pts: &[(f64, f64)], close: bool) -> Option<tiny_skia::Path> {
    let (first, rest) = pts.split_first()?;
    let mut pb = PathBuilder::new();
    pb.move_to(first.0 as f32, first.1 as f32);
    for p in rest {
        pb.line_to(p.0 as f32, p.1 as f32);
    }
    if close {
        pb.close();
    }
    pb.finish()
}

/// Glyph outlines into a path, font units scaled to points and turned y down, placed at
/// (`x`, `y`).
struct Outline<'a> {
    pb: &'a mut PathBuilder,
    k: f32,
    x: f32,
    y: f32,
}

impl Outline<'_> {
    fn at(&self, x: f32, y: f32) -> (f32, f32) {
        (self.x + x * self.k, self.y - y * self.k)
    }
}

impl rustybuzz::ttf_parser::OutlineBuilder for Outline<'_> {
    fn move_to(&mut self, x: f32, y: f32) {
        let (x, y) = self.at(x, y);
        self.pb.move_to(x, y);
    }
    fn line_to(&mut self, x: f32, y: f32) {
        let (x, y) = self.at(x, y);
        self.pb.line_to(x, y);
    }
    fn quad_to(&mut self, x1: f32, y1: f32, x: f32, y: f32) {
        let (a, b) = (self.at(x1, y1), self.at(x, y));
        self.pb.quad_to(a.0, a.1, b.0, b.1);
    }
    fn curve_to(&mut self, x1: f32, y1: f32, x2: f32, y2: f32, x: f32, y: f32) {
        let (a, b, c) = (self.at(x1, y1), self.at(x2, y2), self.at(x, y));
        self.pb.cubic_to(a.0, a.1, b.0, b.1, c.0, c.1);
    }
    fn close(&mut self) {
        self.pb.close();
    }
}

/// `text`'s glyph outlines at `size` points, its baseline starting at the origin.
fn text_path(text: &str, font: Font, size: f64) -> Option<tiny_skia::Path> {
    let (face, glyphs) = shaped(text, font)?;
    let k = size as f32 / face.units_per_em() as f32;
    let mut pb = PathBuilder::new();
    let mut pen = 0.0f32;
    for g in &glyphs {
        let id = rustybuzz::ttf_parser::GlyphId(u16::try_from(g.glyph_id.to_u32()).ok()?);
        let mut o = Outline {
            pb: &mut pb,
            k,
            x: pen + g.x_offset * size as f32,
            y: -g.y_offset * size as f32,
        };
        face.outline_glyph(id, &mut o);
        pen += g.x_advance * size as f32;
    }
    pb.finish()
}

impl Canvas for Raster {
    fn line(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), width: f64, dashed: bool) {
        if let Some(path) = polyline(pts, false) {
            let t = self.transform();
            self.pixmap
                .stroke_path(&path, &paint(rgb, 1.0), &stroke(width, dashed), t, None);
        }
    }

    fn marker(&mut self, x: f64, y: f64, rgb: (u8, u8, u8), hollow: bool) {
        let Some(path) = PathBuilder::from_circle(x as f32, y as f32, MARKER_R as f32) else {
            return;
        };
        let t = self.transform();
        if hollow {
            self.pixmap
                .stroke_path(&path, &paint(rgb, 1.0), &stroke(0.8, false), t, None);
        } else {
            self.pixmap
                .fill_path(&path, &paint(rgb, 1.0), FillRule::Winding, t, None);
        }
    }

    fn band(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64) {
        if let Some(path) = polyline(pts, true) {
            let t = self.transform();
            self.pixmap
                .fill_path(&path, &paint(rgb, opacity), FillRule::Winding, t, None);
        }
    }

    fn text(&mut self, (x, y): (f64, f64), text: &str, st: TextStyle) {
        let shift = st.anchor_shift(text) as f32;
        let Some(path) = text_path(text, st.font(), st.size) else {
            return;
        };
        let (x, y) = (x as f32, y as f32);
        // Along the baseline from the anchor, or turned to read upwards about it.
        let place = if st.up {
            Transform::from_row(0.0, -1.0, 1.0, 0.0, x, y + shift)
        } else {
            Transform::from_translate(x - shift, y)
        };
        let t = place.post_scale(self.scale, self.scale);
        self.pixmap
            .fill_path(&path, &paint((0, 0, 0), 1.0), FillRule::Winding, t, None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::chart::Anchor;
    use crate::report::pdf::text_width;

    /// The pixel at (x, y) points, as RGBA.
    fn at(r: &Raster, x: f64, y: f64) -> [u8; 4] {
        let s = f64::from(r.scale);
        let p = r
            .pixmap
            .pixel((x * s) as u32, (y * s) as u32)
            .expect("inside");
        let c = p.demultiply();
        [c.red(), c.green(), c.blue(), c.alpha()]
    }

    #[test]
    fn shapes_land_where_the_points_say_at_scale() {
        let mut r = Raster::new(100.0, 50.0, 2.0).unwrap();
        assert_eq!((r.pixmap.width(), r.pixmap.height()), (200, 100));
        r.line(&[(10.0, 10.0), (90.0, 10.0)], (200, 0, 0), 2.0, false);
        r.marker(50.0, 30.0, (0, 0, 200), false);
        r.band(
            &[(10.0, 40.0), (30.0, 40.0), (30.0, 48.0), (10.0, 48.0)],
            (0, 200, 0),
            0.5,
        );
        assert_eq!(at(&r, 50.0, 10.0), [200, 0, 0, 255], "on the line");
        assert_eq!(at(&r, 50.0, 20.0), [255, 255, 255, 255], "white off it");
        assert_eq!(at(&r, 50.0, 30.0), [0, 0, 200, 255], "the marker's centre");
        // Half green over white: (255 + 200) / 2 in green, half white elsewhere.
        let half = at(&r, 20.0, 44.0);
        assert!(
            half[1] >= 226 && half[1] <= 229 && half[0] >= 126 && half[0] <= 129,
            "{half:?}"
        );
    }

    #[test]
    fn text_is_inked_where_the_layout_measured_it() {
        let mut r = Raster::new(120.0, 30.0, 2.0).unwrap();
        let st = TextStyle {
            size: 12.0,
            bold: false,
            anchor: Anchor::Start,
            up: false,
        };
        r.text((10.0, 20.0), "µm ″", st);
        let w = text_width("µm ″", Font::Regular, 12.0);
        let inked = |x0: f64, x1: f64| {
            let mut n = 0;
            let mut x = x0;
            while x < x1 {
                for y in [12.0, 14.0, 16.0, 18.0] {
                    if at(&r, x, y)[0] < 128 {
                        n += 1;
                    }
                }
                x += 0.5;
            }
            n
        };
        assert!(inked(10.0, 10.0 + w) > 20, "the glyphs are drawn");
        assert_eq!(inked(0.0, 9.5), 0, "nothing before the anchor");
        assert_eq!(
            inked(10.0 + w + 1.0, 119.0),
            0,
            "nothing past its measured width"
        );
    }

    #[test]
    fn a_picture_of_no_size_is_refused_in_words() {
        let e = Raster::new(0.0, 10.0, 2.0).err().unwrap().to_string();
        assert_eq!(
            e,
            "a picture of 0 × 10 points at 2× has no pixels or too many"
        );
    }
}
