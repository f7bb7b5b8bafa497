//! The acceptance report's content model: a document of blocks (headings, paragraphs,
//! field lists, tables, charts, a signature block) with its text already formatted — numbers
//! at their precision and with units. The three renderers (`render` for HTML and Markdown,
//! `layout` for PDF) only place it; none of them formats a figure.

/// A whole report.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Document {
    pub title: String,
    /// One line under the title (machine, axis, date).
    pub subtitle: String,
    pub blocks: Vec<Block>,
}

impl Document {
    /// End the document with its signature block (a "Signatures" section: `statement`, then a
    /// line for who measured and who accepts for the customer) and number its sections.
    pub fn sign_and_number(&mut self, statement: &str) {
        self.blocks.push(Block::Heading("Signatures".into()));
        self.blocks.push(Block::Paragraph(statement.into()));
        self.blocks.push(Block::Signatures(vec![
            "Measured by".into(),
            "Accepted for the customer by".into(),
        ]));
        let mut n = 0;
        for block in &mut self.blocks {
            if let Block::Heading(h) = block {
                n += 1;
                *h = format!("{n} {h}");
            }
        }
    }
}

/// One block, in reading order.
#[derive(Clone, Debug, PartialEq)]
pub enum Block {
    /// A numbered section heading ("3 Positioning (ISO 230-2)").
    Heading(String),
    /// A heading inside a section.
    Subheading(String),
    Paragraph(String),
    /// Label and value pairs.
    Fields(Vec<(String, String)>),
    Table(Table),
    Chart(Chart),
    /// Signature lines, one per role ("Tested by", "Accepted by").
    Signatures(Vec<String>),
}

/// A table; every row has one cell per column.
#[derive(Clone, Debug, PartialEq)]
pub struct Table {
    pub columns: Vec<Column>,
    pub rows: Vec<Vec<String>>,
    /// A line under the table (what a column's symbol means, the coverage factor).
    pub note: Option<String>,
}

/// A column's heading and alignment.
#[derive(Clone, Debug, PartialEq)]
pub struct Column {
    pub title: String,
    /// Right-aligned (figures).
    pub numeric: bool,
}

impl Column {
    pub fn text(title: &str) -> Column {
        Column {
            title: title.into(),
            numeric: false,
        }
    }
    pub fn number(title: &str) -> Column {
        Column {
            title: title.into(),
            numeric: true,
        }
    }
}

/// A line chart: x is the position along the axis.
#[derive(Clone, Debug, PartialEq)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub lines: Vec<ChartLine>,
    /// Translucent bands under the lines (a ±2s spread).
    pub bands: Vec<ChartBand>,
    /// What the chart shows relative to what (reference line and its slope), under it.
    pub note: String,
}

/// A filled band of a chart: at each x, from `lo` to `hi`.
#[derive(Clone, Debug, PartialEq)]
pub struct ChartBand {
    /// Index into the chart palette.
    pub colour: usize,
    /// 0 (clear) to 1 (solid).
    pub opacity: f64,
    /// (x, lo, hi), in x order.
    pub points: Vec<(f64, f64, f64)>,
}

/// One line of a chart, with its legend entry.
#[derive(Clone, Debug, PartialEq)]
pub struct ChartLine {
    pub label: String,
    /// Index into the chart palette.
    pub colour: usize,
    pub dashed: bool,
    /// Draw a marker at each point.
    pub markers: bool,
    pub points: Vec<(f64, f64)>,
}

/// The chart palette (RGB): blue, orange, green, red, purple, grey.
pub const PALETTE: [(u8, u8, u8); 6] = [
    (31, 90, 180),
    (214, 110, 20),
    (40, 140, 60),
    (190, 40, 40),
    (120, 70, 160),
    (110, 110, 110),
];

/// The palette colour `i` (wrapping).
pub fn colour(i: usize) -> (u8, u8, u8) {
    PALETTE[i % PALETTE.len()]
}
