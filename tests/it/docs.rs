//! The user guide (`docs/`, mdBook) and the README front page: every page is in the book's
//! summary, every link between pages reaches a page and a heading that exist, the README
//! starts with the two commands and stays a front page, and the configuration reference is
//! the one `axiscomp config reference` writes. (`.ci/run` builds the book with mdbook too.)

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The guide's pages (paths relative to `docs/src`).
fn pages() -> Vec<PathBuf> {
    fn walk(dir: &Path, base: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.expect("entry").path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, base, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p.strip_prefix(base).expect("under src").to_path_buf());
            }
        }
    }
    let src = root().join("docs/src");
    let mut out = Vec::new();
    walk(&src, &src, &mut out);
    out
}

/// The lines of `text` outside fenced code blocks.
fn prose(text: &str) -> Vec<&str> {
    let mut fenced = false;
    text.lines()
        .filter(|l| {
            if l.trim_start().starts_with("```") {
                fenced = !fenced;
                return false;
            }
            !fenced
        })
        .collect()
}

/// A line without its inline code spans (a link written in code is not a link).
fn without_code(line: &str) -> String {
    line.split('`').step_by(2).collect::<Vec<_>>().join("")
}

/// Every `[text](target)` of `text`'s prose.
fn links(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in prose(text) {
        let line = without_code(line);
        let mut rest = line.as_str();
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            if let Some(end) = rest.find(')') {
                out.push(rest[..end].trim().to_string());
                rest = &rest[end..];
            }
        }
    }
    out
}

/// The anchors mdBook gives `text`'s headings: the heading's words lower-cased, spaces to
/// `-`, other punctuation dropped, and `-1`, `-2`, … after a repeat.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut out = BTreeSet::new();
    for line in prose(text) {
        let Some(h) = line.strip_prefix('#') else {
            continue;
        };
        let words = h.trim_start_matches('#').trim();
        // Link text only: `[words](target)` reads as `words`.
        let mut plain = String::new();
        let mut rest = words;
        while let Some(i) = rest.find('[') {
            plain.push_str(&rest[..i]);
            rest = &rest[i + 1..];
            match (rest.find("]("), rest.find(')')) {
                (Some(a), Some(b)) if a < b => {
                    plain.push_str(&rest[..a]);
                    rest = &rest[b + 1..];
                }
                _ => plain.push('['),
            }
        }
        plain.push_str(rest);
        let id: String = plain
            .chars()
            .filter_map(|c| {
                if c.is_alphanumeric() || c == '_' || c == '-' {
                    Some(c.to_lowercase().next().unwrap_or(c))
                } else if c.is_whitespace() {
                    Some('-')
                } else {
                    None
                }
            })
            .collect();
        let n = seen.entry(id.clone()).or_insert(0);
        out.insert(if *n == 0 {
            id.clone()
        } else {
            format!("{id}-{n}")
        });
        *n += 1;
    }
    out
}

#[test]
fn every_page_is_in_the_summary_and_every_link_reaches_a_heading() {
    let src = root().join("docs/src");
    let summary = read(&src.join("SUMMARY.md"));
    let listed: BTreeSet<PathBuf> = links(&summary)
        .iter()
        .filter(|l| !l.is_empty())
        .map(PathBuf::from)
        .collect();
    let all = pages();
    assert!(all.len() >= 10, "{} pages", all.len());
    for p in &all {
        if p != Path::new("SUMMARY.md") {
            assert!(
                listed.contains(p),
                "docs/src/{} is not in SUMMARY.md",
                p.display()
            );
        }
    }
    let mut bad = Vec::new();
    let mut checked = 0;
    for p in all
        .iter()
        .chain(std::iter::once(&PathBuf::from("SUMMARY.md")))
    {
        let text = read(&src.join(p));
        let dir = p.parent().unwrap_or(Path::new(""));
        for l in links(&text) {
            if l.starts_with("http://") || l.starts_with("https://") || l.starts_with("mailto:") {
                continue;
            }
            let (file, anchor) = match l.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (l.as_str(), None),
            };
            let target = if file.is_empty() {
                p.clone()
            } else {
                dir.join(file)
            };
            let Ok(body) = std::fs::read_to_string(src.join(&target)) else {
                bad.push(format!(
                    "{}: {l}: no page {}",
                    p.display(),
                    target.display()
                ));
                continue;
            };
            if let Some(a) = anchor
                && !anchors(&body).contains(a)
            {
                bad.push(format!(
                    "{}: {l}: {} has no heading #{a}",
                    p.display(),
                    target.display()
                ));
            }
            checked += 1;
        }
    }
    assert!(
        bad.is_empty(),
        "broken links in docs/src:\n{}",
        bad.join("\n")
    );
    assert!(checked > 20, "{checked} links checked");
}

#[test]
fn the_anchor_rule_is_mdbooks() {
    let a = anchors(
        "# Every capture true or flagged\n## `[tracking]` keys\n## Re-measuring\n\
         ```\n# not a heading\n```\n## Re-measuring\n## [The demo](demo.md): µm\n",
    );
    let want: BTreeSet<String> = [
        "every-capture-true-or-flagged",
        "tracking-keys",
        "re-measuring",
        "re-measuring-1",
        "the-demo-µm",
    ]
    .map(String::from)
    .into();
    assert_eq!(a, want);
    assert_eq!(
        links("see [a](a.md#x) and `[b](b.md)`\n```\n[c](c.md)\n```\n"),
        ["a.md#x"]
    );
}

#[test]
fn the_readme_is_a_front_page_that_starts_with_the_two_commands() {
    let readme = read(&root().join("README.md"));
    let lines: Vec<&str> = readme.lines().collect();
    assert!(lines.len() < 120, "README.md has {} lines", lines.len());
    let head = lines[..8.min(lines.len())].join("\n");
    assert!(
        head.contains("cargo run --release -- demo") && head.contains("cargo test"),
        "{head}"
    );
    assert!(
        readme.contains("mdbook build docs"),
        "README names the guide"
    );
}

#[test]
fn the_configuration_page_is_what_the_binary_writes() {
    let out = crate::helpers::run(&["config", "reference"], "");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let page = read(&root().join("docs/src/reference/configuration.md"));
    assert!(
        String::from_utf8_lossy(&out.stdout) == page,
        "docs/src/reference/configuration.md is not `axiscomp config reference`'s output: \
         write it again with `cargo run -- config reference > docs/src/reference/configuration.md`"
    );
    let example = crate::helpers::run(&["config", "example"], "");
    assert_eq!(
        String::from_utf8_lossy(&example.stdout),
        read(&root().join("configs/axiscomp.toml"))
    );
}
