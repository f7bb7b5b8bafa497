//! The acceptance document on A4 pages: margins, a running footer ("page n of m"), headings
//! kept with what follows, tables whose column widths fit their content and whose heading row
//! repeats after a page break, charts drawn as vector paths, and the signature block.

use super::chart::{self, TextStyle};
use super::doc::{Block, Chart, Document, Table};
use super::pdf::{self, Font, PAGE_H, PAGE_W, Page, text_width};

const MARGIN: f64 = 50.0;
const BOTTOM: f64 = PAGE_H - 56.0;
const BODY: f64 = 9.0;
const CELL: f64 = 8.0;
/// Notes under tables and charts.
const NOTE: f64 = 7.5;
const ROW_H: f64 = 11.5;
const TEXT_W: f64 = PAGE_W - 2.0 * MARGIN;
const CHART_PLOT_H: f64 = 150.0;

struct Flow {
    pages: Vec<Page>,
    y: f64,
}

impl Flow {
    fn page(&mut self) -> &mut Page {
        if self.pages.is_empty() {
            self.pages.push(Page::default());
        }
        let last = self.pages.len() - 1;
        &mut self.pages[last]
    }
    fn new_page(&mut self) {
        self.pages.push(Page::default());
        self.y = MARGIN;
    }
    /// Start a new page unless `h` more fits.
    fn need(&mut self, h: f64) {
        if self.y + h > BOTTOM && self.y > MARGIN + 1.0 {
            self.new_page();
        }
    }
}

/// Split `s` into lines no wider than `w`.
pub fn wrap(s: &str, font: Font, size: f64, w: f64) -> Vec<String> {
    let mut lines = Vec::new();
    let mut line = String::new();
    for word in s.split_whitespace() {
        let candidate = if line.is_empty() {
            word.to_string()
        } else {
            format!("{line} {word}")
        };
        if !line.is_empty() && text_width(&candidate, font, size) > w {
            lines.push(std::mem::take(&mut line));
            line = word.to_string();
        } else {
            line = candidate;
        }
    }
    if !line.is_empty() {
        lines.push(line);
    }
    lines
}

fn paragraph(f: &mut Flow, s: &str, font: Font, size: f64) {
    for l in wrap(s, font, size, TEXT_W) {
        f.need(size + 3.0);
        f.y += size + 3.0;
        let y = f.y;
        f.page().text(MARGIN, y, &l, font, size);
    }
}

fn fields(f: &mut Flow, rows: &[(String, String)]) {
    let label_w = rows
        .iter()
        .map(|(k, _)| text_width(k, Font::Bold, BODY))
        .fold(0.0, f64::max)
        .min(TEXT_W * 0.4)
        + 12.0;
    for (k, v) in rows {
        let lines = wrap(v, Font::Regular, BODY, TEXT_W - label_w);
        f.need(ROW_H * lines.len().max(1) as f64);
        f.y += ROW_H;
        let y = f.y;
        f.page().text(MARGIN, y, k, Font::Bold, BODY);
        for (i, l) in lines.iter().enumerate() {
            if i > 0 {
                f.y += ROW_H;
            }
            let y = f.y;
            f.page().text(MARGIN + label_w, y, l, Font::Regular, BODY);
        }
    }
    f.y += 4.0;
}

/// Column widths: each column's widest cell, scaled down to the text width when wider.
fn column_widths(t: &Table) -> Vec<f64> {
    let mut w: Vec<f64> = t
        .columns
        .iter()
        .map(|c| text_width(&c.title, Font::Bold, CELL) + 10.0)
        .collect();
    for row in &t.rows {
        for (i, cell) in row.iter().enumerate().take(w.len()) {
            w[i] = w[i].max(text_width(cell, Font::Regular, CELL) + 10.0);
        }
    }
    let total: f64 = w.iter().sum();
    if total > TEXT_W {
        w.iter_mut().for_each(|x| *x *= TEXT_W / total);
    }
    w
}

fn table_row(f: &mut Flow, cells: &[String], t: &Table, widths: &[f64], font: Font) {
    let y = f.y;
    let mut x = MARGIN;
    for ((cell, col), w) in cells.iter().zip(&t.columns).zip(widths) {
        // A cell too wide for its scaled column is cut with an ellipsis.
        let mut s = cell.clone();
        while text_width(&s, font, CELL) > w - 4.0 && s.chars().count() > 2 {
            s.pop();
            s.pop();
            s.push('…');
        }
        let tw = text_width(&s, font, CELL);
        let tx = if col.numeric {
            x + w - 5.0 - tw
        } else {
            x + 2.0
        };
        f.page().text(tx, y, &s, font, CELL);
        x += w;
    }
}

fn rule(f: &mut Flow, y: f64, width: f64, grey: u8) {
    let p = f.page();
    p.stroke_style((grey, grey, grey), width, false);
    p.polyline(&[(MARGIN, y), (PAGE_W - MARGIN, y)]);
}

fn table(f: &mut Flow, t: &Table) {
    let widths = column_widths(t);
    let titles: Vec<String> = t.columns.iter().map(|c| c.title.clone()).collect();
    let head = |f: &mut Flow| {
        f.y += ROW_H;
        table_row(f, &titles, t, &widths, Font::Bold);
        let y = f.y + 3.5;
        rule(f, y, 0.6, 90);
    };
    // The note stays on the page of the last row.
    let note_h = t.note.as_ref().map_or(0.0, |n| {
        wrap(n, Font::Regular, NOTE, TEXT_W).len() as f64 * (NOTE + 3.0) + 8.0
    });
    // A short table is kept whole; a long one starts with a few rows.
    if t.rows.len() <= 12 {
        f.need(ROW_H * (t.rows.len() + 1) as f64 + 8.0 + note_h);
    } else {
        f.need(ROW_H * 3.0);
    }
    head(f);
    for (i, row) in t.rows.iter().enumerate() {
        let last = i + 1 == t.rows.len();
        if f.y + ROW_H + if last { note_h } else { 0.0 } > BOTTOM {
            f.new_page();
            head(f);
        }
        f.y += ROW_H;
        table_row(f, row, t, &widths, Font::Regular);
    }
    let y = f.y + 3.5;
    rule(f, y, 0.4, 160);
    f.y += 4.0;
    if let Some(note) = &t.note {
        paragraph(f, note, Font::Regular, NOTE);
    }
    f.y += 6.0;
}

/// A chart drawn on a page with its box's top-left at `at`.
struct OnPage<'a> {
    page: &'a mut Page,
    at: (f64, f64),
}

impl chart::Canvas for OnPage<'_> {
    fn line(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), width: f64, dashed: bool) {
        self.page.stroke_style(rgb, width, dashed);
        let (x, y) = self.at;
        let moved: Vec<(f64, f64)> = pts.iter().map(|(a, b)| (a + x, b + y)).collect();
        self.page.polyline(&moved);
    }
    fn marker(&mut self, mx: f64, my: f64, rgb: (u8, u8, u8), hollow: bool) {
        let (x, y) = self.at;
        if hollow {
            self.page.stroke_style(rgb, 0.6, false);
        }
        self.page.fill(rgb);
        self.page.circle(mx + x, my + y, chart::MARKER_R, !hollow);
        self.page.fill((0, 0, 0));
    }
    fn band(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64) {
        let (x, y) = self.at;
        let moved: Vec<(f64, f64)> = pts.iter().map(|(a, b)| (a + x, b + y)).collect();
        self.page.polygon(&moved, rgb, opacity);
    }
    fn text(&mut self, (tx, ty): (f64, f64), text: &str, st: TextStyle) {
        let (x, y) = self.at;
        let (font, shift) = (st.font(), st.anchor_shift(text));
        if st.up {
            self.page
                .text_up(tx + x, ty + y + shift, text, font, st.size);
        } else {
            self.page.text(tx + x - shift, ty + y, text, font, st.size);
        }
    }
}

fn chart_block(f: &mut Flow, c: &Chart) {
    let h = chart::height(c, TEXT_W, CHART_PLOT_H);
    let note_lines = wrap(&c.note, Font::Regular, NOTE, TEXT_W).len() as f64;
    f.need(h + note_lines * 10.5 + 8.0);
    let at = (MARGIN, f.y + 4.0);
    chart::draw(c, TEXT_W, CHART_PLOT_H, &mut OnPage { page: f.page(), at });
    f.y += h + 2.0;
    if !c.note.is_empty() {
        paragraph(f, &c.note, Font::Regular, NOTE);
    }
    f.y += 8.0;
}

fn signatures(f: &mut Flow, roles: &[String]) {
    f.need(56.0 * roles.len() as f64);
    for role in roles {
        f.y += 22.0;
        let y = f.y;
        let p = f.page();
        p.text(MARGIN, y, role, Font::Bold, BODY);
        let line_y = y + 26.0;
        p.stroke_style((0, 0, 0), 0.5, false);
        p.polyline(&[(MARGIN, line_y), (MARGIN + 280.0, line_y)]);
        p.polyline(&[(MARGIN + 320.0, line_y), (PAGE_W - MARGIN, line_y)]);
        p.text(
            MARGIN,
            line_y + 9.0,
            "Name and signature",
            Font::Regular,
            7.0,
        );
        p.text(MARGIN + 320.0, line_y + 9.0, "Date", Font::Regular, 7.0);
        f.y = line_y + 12.0;
    }
}

/// The document as pages (without the footer).
fn pages(doc: &Document) -> Vec<Page> {
    let mut f = Flow {
        pages: vec![Page::default()],
        y: MARGIN,
    };
    paragraph(&mut f, &doc.title, Font::Bold, 16.0);
    f.y += 4.0;
    paragraph(&mut f, &doc.subtitle, Font::Regular, 10.0);
    f.y += 6.0;
    let y = f.y;
    rule(&mut f, y, 1.0, 0);
    f.y += 4.0;
    for b in &doc.blocks {
        match b {
            Block::Heading(s) => {
                // Keep a heading with at least a few lines of what follows.
                f.need(80.0);
                f.y += 10.0;
                paragraph(&mut f, s, Font::Bold, 12.0);
                f.y += 2.0;
            }
            Block::Subheading(s) => {
                // With room for a short table under it (the table is kept whole).
                f.need(180.0);
                f.y += 4.0;
                paragraph(&mut f, s, Font::Bold, 9.5);
            }
            Block::Paragraph(s) => {
                paragraph(&mut f, s, Font::Regular, BODY);
                f.y += 3.0;
            }
            Block::Fields(rows) => fields(&mut f, rows),
            Block::Table(t) => table(&mut f, t),
            Block::Chart(c) => chart_block(&mut f, c),
            Block::Signatures(roles) => signatures(&mut f, roles),
        }
    }
    f.pages
}

/// The document as a PDF file (PDF/A-2b).
pub fn pdf(doc: &Document, info: &pdf::Info) -> Result<Vec<u8>, pdf::PdfError> {
    let mut pages = pages(doc);
    let count = pages.len();
    for (i, p) in pages.iter_mut().enumerate() {
        let y = PAGE_H - 30.0;
        p.stroke_style((150, 150, 150), 0.4, false);
        p.polyline(&[(MARGIN, y - 10.0), (PAGE_W - MARGIN, y - 10.0)]);
        p.text(MARGIN, y, &doc.title, Font::Regular, 7.0);
        let s = format!("page {} of {count}", i + 1);
        let w = text_width(&s, Font::Regular, 7.0);
        p.text(PAGE_W - MARGIN - w, y, &s, Font::Regular, 7.0);
    }
    pdf::write(&pages, info)
}
