//! The configuration reference (the guide's `docs/src/reference/configuration.md`, and
//! `axiscomp config reference`), generated from the configuration's own definitions so that it
//! cannot drift from them: the keys and their built-in defaults are what [`RawConfig`] reads
//! from [`DEFAULTS`] (each section's struct, serialised back), and each key's words are the
//! comments beside it in the documented example `configs/axiscomp.toml` ([`EXAMPLE`], carried
//! in the binary). A key the code has and the example does not document, or one the example
//! has and the code does not, is an error naming it: the reference is not written.

use super::{DEFAULTS, ENV_PREFIX, RawConfig};
use std::collections::BTreeSet;
use std::fmt::Write as _;
use thiserror::Error;

/// The documented example configuration (`configs/axiscomp.toml`).
pub const EXAMPLE: &str = include_str!("../../configs/axiscomp.toml");

/// Why the reference cannot be written.
#[derive(Debug, Error, PartialEq)]
pub enum ReferenceError {
    #[error("the built-in defaults do not read as the configuration: {0}")]
    Defaults(String),
    #[error(
        "configs/axiscomp.toml line {line}: {problem}; every key of the configuration is \
         documented there once, with a comment above it or beside it"
    )]
    Example { line: usize, problem: String },
    #[error(
        "{key} is a key of the configuration but configs/axiscomp.toml does not have it: add it \
         there with its default and a comment"
    )]
    Undocumented { key: String },
}

/// One group of keys of the example: the keys that follow one comment block with no blank
/// line between them (`operator_group`, `viewer_group`), and the words that describe them.
#[derive(Debug, Default)]
struct Group {
    words: Vec<String>,
    keys: Vec<Entry>,
}

#[derive(Debug)]
struct Entry {
    key: String,
    /// The example's value when it is not the built-in default.
    example: String,
    /// Its comment on the same line.
    inline: Option<String>,
    /// A key left out of the example (`# key = value  # words`): absent by default.
    optional: bool,
}

/// A section of the example: its header's comment block and its groups.
#[derive(Debug, Default)]
struct Section {
    name: String,
    words: Vec<String>,
    groups: Vec<Group>,
}

impl Section {
    /// `entry` into the group the last key opened (`open`: no blank line or comment since),
    /// else into a new group described by the `comments` gathered above it.
    fn add(&mut self, entry: Entry, open: bool, comments: &mut Vec<String>) {
        match self.groups.last_mut() {
            Some(g) if open && comments.is_empty() => g.keys.push(entry),
            _ => self.groups.push(Group {
                words: std::mem::take(comments),
                keys: vec![entry],
            }),
        }
    }
}

/// `key = value  # words` split, the comment outside any string.
fn split_comment(s: &str) -> (&str, Option<&str>) {
    let mut quote = None;
    for (i, c) in s.char_indices() {
        match (quote, c) {
            (None, '"' | '\'') => quote = Some(c),
            (Some(q), c) if c == q => quote = None,
            (None, '#') => return (s[..i].trim_end(), Some(s[i + 1..].trim())),
            _ => {}
        }
    }
    (s.trim_end(), None)
}

/// `key = value` (a bare TOML key and its value's text).
fn key_value(s: &str) -> Option<(&str, &str)> {
    let (k, v) = s.split_once('=')?;
    let k = k.trim();
    let bare = !k.is_empty()
        && k.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    bare.then(|| (k, v.trim()))
}

/// The example read into sections, groups and keys.
fn sections(example: &str) -> Result<Vec<Section>, ReferenceError> {
    let mut out: Vec<Section> = Vec::new();
    let mut comments: Vec<String> = Vec::new();
    // The group the last key went into, while no blank line or comment has come since.
    let mut open = false;
    for (i, raw) in example.lines().enumerate() {
        let line = raw.trim();
        let err = |problem: String| ReferenceError::Example {
            line: i + 1,
            problem,
        };
        if line.is_empty() {
            // A comment block followed by a blank line describes neither the next key nor
            // the next section (the file's header, a note between sections).
            comments.clear();
            open = false;
            continue;
        }
        if let Some(text) = line.strip_prefix('#') {
            let text = text.strip_prefix(' ').unwrap_or(text);
            // `# key = value  # words`: a key the example leaves out (absent by default).
            if let Some(section) = out.last_mut()
                && let (kv, Some(words)) = split_comment(text)
                && let Some((key, value)) = key_value(kv)
            {
                let entry = Entry {
                    key: key.to_string(),
                    example: value.to_string(),
                    inline: Some(words.to_string()),
                    optional: true,
                };
                section.add(entry, open, &mut comments);
                open = true;
                continue;
            }
            comments.push(text.to_string());
            open = false;
            continue;
        }
        if let Some(name) = line.strip_prefix('[') {
            let name = name
                .strip_suffix(']')
                .ok_or_else(|| err(format!("\"{line}\" is not a section header")))?;
            out.push(Section {
                name: name.trim().to_string(),
                words: std::mem::take(&mut comments),
                groups: Vec::new(),
            });
            open = false;
            continue;
        }
        let (kv, inline) = split_comment(line);
        let (key, value) = key_value(kv).ok_or_else(|| {
            err(format!(
                "\"{line}\" is neither a comment, a section nor a key"
            ))
        })?;
        let section = out
            .last_mut()
            .ok_or_else(|| err(format!("{key} comes before any [section]")))?;
        let entry = Entry {
            key: key.to_string(),
            example: value.to_string(),
            inline: inline.map(str::to_string),
            optional: false,
        };
        section.add(entry, open, &mut comments);
        open = true;
    }
    Ok(out)
}

/// Every key (dotted) and its built-in default, as the code reads the defaults.
fn defaults() -> Result<toml::Table, ReferenceError> {
    let raw: RawConfig =
        toml::from_str(DEFAULTS).map_err(|e| ReferenceError::Defaults(e.to_string()))?;
    match toml::Value::try_from(&raw) {
        Ok(toml::Value::Table(t)) => Ok(t),
        Ok(_) => Err(ReferenceError::Defaults("not a table".into())),
        Err(e) => Err(ReferenceError::Defaults(e.to_string())),
    }
}

fn flatten(t: &toml::Table, prefix: &str, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in t {
        let key = format!("{prefix}{k}");
        match v {
            toml::Value::Table(inner) => flatten(inner, &format!("{key}."), out),
            v => out.push((key, v.clone())),
        }
    }
}

/// Whether the example's value text is the built-in default (numbers compared as numbers:
/// `0` is `0.0`).
fn same(default: Option<&toml::Value>, example: &str) -> bool {
    let parsed = toml::from_str::<toml::Table>(&format!("v = {example}"))
        .ok()
        .and_then(|mut t| t.remove("v"));
    let number = |v: &toml::Value| match v {
        toml::Value::Integer(i) => Some(*i as f64),
        toml::Value::Float(f) => Some(*f),
        _ => None,
    };
    match (default, parsed) {
        (Some(d), Some(p)) => match (number(d), number(&p)) {
            (Some(a), Some(b)) => a == b,
            _ => *d == p,
        },
        _ => false,
    }
}

/// The environment variable that sets `key` (`io.rate_hz`: `AXISCOMP__IO__RATE_HZ`).
fn env_var(key: &str) -> String {
    format!(
        "{ENV_PREFIX}__{}",
        key.replace('.', "__").to_ascii_uppercase()
    )
}

/// Words of a comment block as one paragraph (the example wraps at 100 columns).
fn paragraph(lines: &[String]) -> String {
    words(&lines.join(" "))
}

/// Comment text as Markdown prose: outside its code spans, `<` is escaped (`runs/<id>/` is a
/// path, not an HTML tag) and `|` too.
fn words(text: &str) -> String {
    text.split('`')
        .enumerate()
        .map(|(i, part)| {
            if i % 2 == 1 {
                part.to_string()
            } else {
                part.replace('<', "\\<").replace('|', "\\|")
            }
        })
        .collect::<Vec<_>>()
        .join("`")
}

/// The reference in Markdown.
pub fn markdown() -> Result<String, ReferenceError> {
    let mut code = Vec::new();
    flatten(&defaults()?, "", &mut code);
    let defaults: std::collections::BTreeMap<String, toml::Value> = code.into_iter().collect();
    let sections = sections(EXAMPLE)?;
    let mut documented = BTreeSet::new();
    let mut md = String::new();
    md.push_str(
        "# Configuration reference\n\n\
         <!-- Generated by `axiscomp config reference` from the configuration's definitions \
         (its keys and built-in defaults in the code, its words in configs/axiscomp.toml); a \
         test fails when this page differs. Do not edit by hand. -->\n\n\
         The service reads its configuration in layers, lowest first: the built-in defaults, \
         `/etc/axiscomp/axiscomp.toml`, the file given with `--config FILE`, then environment \
         variables `AXISCOMP__SECTION__KEY`. An unknown key is an error. \
         `axiscomp check --config FILE` checks a file and every file it names, offline; \
         `axiscomp config example` prints the documented example, `configs/axiscomp.toml`.\n\n\
         Each key below gives its built-in default and the variable that sets it; where the \
         example sets another value, that value too.\n",
    );
    for s in &sections {
        let _ = write!(md, "\n## [{}]\n", s.name);
        if !s.words.is_empty() {
            let _ = write!(md, "\n{}\n", paragraph(&s.words));
        }
        for g in &s.groups {
            let names: Vec<String> = g.keys.iter().map(|e| format!("`{}`", e.key)).collect();
            let _ = write!(md, "\n### {}\n\n", names.join(", "));
            for e in &g.keys {
                let key = format!("{}.{}", s.name, e.key);
                let default = match (defaults.get(&key), e.optional) {
                    (Some(v), _) => format!("`{v}`"),
                    (None, true) => "absent".to_string(),
                    (None, false) => {
                        return Err(ReferenceError::Example {
                            line: line_of(&key),
                            problem: format!("{key} is not a key of the configuration"),
                        });
                    }
                };
                documented.insert(key.clone());
                let single = g.keys.len() == 1;
                let mut row = if single {
                    format!("Default {default}")
                } else {
                    format!("- `{}`: default {default}", e.key)
                };
                if !e.optional && !same(defaults.get(&key), &e.example) {
                    let _ = write!(row, "; example `{}`", e.example);
                }
                let _ = write!(row, "; set by `{}`", env_var(&key));
                if let Some(w) = &e.inline {
                    let _ = write!(row, ". {}", words(w));
                } else if single {
                    row.push('.');
                }
                md.push_str(&row);
                md.push('\n');
            }
            if !g.words.is_empty() {
                let _ = write!(md, "\n{}\n", paragraph(&g.words));
            }
        }
    }
    if let Some(key) = defaults.keys().find(|k| !documented.contains(*k)) {
        return Err(ReferenceError::Undocumented { key: key.clone() });
    }
    Ok(md)
}

/// The example's line of `key` (dotted), for an error; 0 when not found.
fn line_of(key: &str) -> usize {
    let (section, name) = key.rsplit_once('.').unwrap_or(("", key));
    let mut current = "";
    for (i, line) in EXAMPLE.lines().enumerate() {
        let t = line.trim();
        if let Some(s) = t.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
            current = s;
        } else if current == section
            && key_value(split_comment(t.trim_start_matches("# ")).0).map(|(k, _)| k) == Some(name)
        {
            return i + 1;
        }
    }
    0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The guide's page, as committed.
    const PAGE: &str = "docs/src/reference/configuration.md";

    #[test]
    fn the_guides_page_is_the_generated_reference() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(PAGE);
        let page = std::fs::read_to_string(&path).unwrap_or_default();
        let generated = markdown().expect("the reference");
        assert!(
            page == generated,
            "{PAGE} differs from the configuration's definitions: write it again with \
             `cargo run -- config reference > {PAGE}`"
        );
    }

    #[test]
    fn every_key_in_the_code_is_in_the_reference_with_its_default() {
        let md = markdown().expect("the reference");
        let mut keys = Vec::new();
        flatten(&defaults().expect("defaults"), "", &mut keys);
        assert!(keys.len() > 150, "{} keys", keys.len());
        for (key, value) in keys {
            let (section, name) = key.rsplit_once('.').expect("dotted");
            let at = md.find(&format!("\n## [{section}]\n")).expect(&key);
            let bullet = format!("- `{name}`: default `{value}`");
            let alone = format!("### `{name}`\n\nDefault `{value}`");
            assert!(
                md[at..].contains(&bullet) || md[at..].contains(&alone),
                "{key}: no line {bullet}"
            );
            assert!(md.contains(&env_var(&key)), "{key}");
        }
        assert_eq!(env_var("io.rate_hz"), "AXISCOMP__IO__RATE_HZ");
    }

    #[test]
    fn groups_comments_and_inline_words() {
        let s = sections(
            "# header\n\n[a]\n# Two keys.\nx = 1\ny = \"#2\"   # y's own\n\n# c alone\nc = 3\n\
             # opt = 4   # absent unless set\n",
        )
        .expect("read");
        assert_eq!(s.len(), 1);
        assert!(s[0].words.is_empty(), "the header's block is the file's");
        let g = &s[0].groups;
        assert_eq!(g.len(), 2);
        assert_eq!(g[0].words, vec!["Two keys."]);
        assert_eq!(
            g[0].keys.iter().map(|e| e.key.as_str()).collect::<Vec<_>>(),
            ["x", "y"]
        );
        assert_eq!(g[0].keys[1].example, "\"#2\"");
        assert_eq!(g[0].keys[1].inline.as_deref(), Some("y's own"));
        assert_eq!(g[1].words, vec!["c alone"]);
        assert_eq!(g[1].keys[1].key, "opt");
        assert!(g[1].keys[1].optional);
    }

    #[test]
    fn prose_escapes_what_markdown_would_read_as_html() {
        assert_eq!(
            words("programs in runs/<id>/ (`runs/<id>/`), a | b"),
            "programs in runs/\\<id>/ (`runs/<id>/`), a \\| b"
        );
    }

    #[test]
    fn a_bad_line_is_named() {
        assert_eq!(
            sections("[a]\nthis is not toml\n").unwrap_err(),
            ReferenceError::Example {
                line: 2,
                problem: "\"this is not toml\" is neither a comment, a section nor a key".into()
            }
        );
    }
}
