//! A tiny well-formedness checker for the tests (no XML crate): tags must nest and close,
//! attributes must be quoted, `&` must start an entity, `<` must not appear in text or values.
//! It records every element with its attributes and the text content, so tests can count
//! elements and look for strings. Declarations (`<?…?>`, `<!…>`) and comments are skipped.

/// One element as opened.
#[derive(Debug, Clone)]
pub struct Element {
    pub name: String,
    pub attrs: Vec<(String, String)>,
}

impl Element {
    pub fn attr(&self, name: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }
}

/// A parsed document: elements in document order, and the text nodes.
#[derive(Debug, Default)]
pub struct Doc {
    pub root: String,
    pub elements: Vec<Element>,
    pub texts: Vec<String>,
}

impl Doc {
    pub fn count(&self, name: &str) -> usize {
        self.elements.iter().filter(|e| e.name == name).count()
    }
    pub fn named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Element> + 'a {
        self.elements.iter().filter(move |e| e.name == name)
    }
    pub fn has_text(&self, needle: &str) -> bool {
        self.texts.iter().any(|t| t.contains(needle))
    }
}

fn check_entities(s: &str, at: usize) -> Result<(), String> {
    let mut rest = s;
    while let Some(i) = rest.find('&') {
        let after = &rest[i + 1..];
        let end = after
            .find(';')
            .ok_or(format!("bare & near byte {at}: {:?}", &rest[i..]))?;
        let name = &after[..end];
        let ok = match name.strip_prefix('#') {
            Some(num) => !num.is_empty() && num.chars().all(|c| c.is_ascii_digit()),
            None => !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric()),
        };
        if !ok {
            return Err(format!("bad entity &{name}; near byte {at}"));
        }
        rest = &after[end + 1..];
    }
    Ok(())
}

fn is_name_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | ':' | '.')
}

/// Parse `s`; `Err` names the first problem.
pub fn parse(s: &str) -> Result<Doc, String> {
    let mut doc = Doc::default();
    let mut stack: Vec<String> = Vec::new();
    let mut i = 0;
    let b = s.as_bytes();
    while i < s.len() {
        if b[i] != b'<' {
            let end = s[i..].find('<').map_or(s.len(), |j| i + j);
            let t = &s[i..end];
            if !t.trim().is_empty() {
                if stack.is_empty() {
                    return Err(format!("text outside the root at byte {i}: {t:?}"));
                }
                check_entities(t, i)?;
                doc.texts.push(t.to_string());
            }
            i = end;
            continue;
        }
        let rest = &s[i..];
        if let Some(r) = rest.strip_prefix("<!--") {
            let end = r.find("-->").ok_or("unclosed comment")?;
            i += 4 + end + 3;
        } else if rest.starts_with("<?") || rest.starts_with("<!") {
            let end = rest.find('>').ok_or("unclosed declaration")?;
            i += end + 1;
        } else if let Some(r) = rest.strip_prefix("</") {
            let end = r.find('>').ok_or(format!("unclosed end tag at byte {i}"))?;
            let name = r[..end].trim();
            match stack.pop() {
                Some(open) if open == name => {}
                Some(open) => {
                    return Err(format!("</{name}> at byte {i} closes <{open}>"));
                }
                None => return Err(format!("</{name}> at byte {i} closes nothing")),
            }
            i += 2 + end + 1;
        } else {
            let r = &rest[1..];
            let name_len = r.find(|c: char| !is_name_char(c)).unwrap_or(r.len());
            if name_len == 0 {
                return Err(format!("bare < at byte {i}"));
            }
            let name = r[..name_len].to_string();
            if stack.is_empty() {
                if !doc.root.is_empty() {
                    return Err(format!("second root <{name}> at byte {i}"));
                }
                doc.root = name.clone();
            }
            let mut j = 1 + name_len;
            let mut attrs = Vec::new();
            let closed;
            loop {
                let t = &rest[j..];
                let ws = t.len() - t.trim_start().len();
                j += ws;
                let t = &rest[j..];
                if t.starts_with("/>") {
                    closed = true;
                    j += 2;
                    break;
                }
                if t.starts_with('>') {
                    closed = false;
                    j += 1;
                    break;
                }
                if ws == 0 {
                    return Err(format!("<{name}> at byte {i}: attributes need spaces"));
                }
                let eq = t
                    .find('=')
                    .ok_or(format!("<{name}> at byte {i}: attribute without value"))?;
                let key = t[..eq].trim().to_string();
                if key.is_empty() || !key.chars().all(is_name_char) {
                    return Err(format!("<{name}> at byte {i}: bad attribute name {key:?}"));
                }
                let v = &t[eq + 1..];
                let quote = v.chars().next().ok_or("truncated attribute")?;
                if quote != '"' && quote != '\'' {
                    return Err(format!("<{name}> at byte {i}: unquoted attribute {key}"));
                }
                let vend = v[1..].find(quote).ok_or(format!(
                    "<{name}> at byte {i}: unterminated attribute {key}"
                ))?;
                let value = &v[1..1 + vend];
                if value.contains('<') {
                    return Err(format!("<{name}> at byte {i}: < in attribute {key}"));
                }
                check_entities(value, i)?;
                attrs.push((key, value.to_string()));
                j += eq + 1 + 1 + vend + 1;
            }
            doc.elements.push(Element {
                name: name.clone(),
                attrs,
            });
            if !closed {
                stack.push(name);
            }
            i += j;
        }
    }
    if let Some(open) = stack.pop() {
        return Err(format!("<{open}> is never closed"));
    }
    if doc.root.is_empty() {
        return Err("no root element".into());
    }
    Ok(doc)
}

#[cfg(test)]
mod tests {
    use super::parse;

    #[test]
    fn accepts_well_formed_and_rejects_the_rest() {
        let d =
            parse("<?xml version=\"1.0\"?><a x=\"1\"><b/><b y='&amp;'>t &lt; u</b></a>").unwrap();
        assert_eq!(d.root, "a");
        assert_eq!(d.count("b"), 2);
        assert_eq!(d.named("b").nth(1).unwrap().attr("y"), Some("&amp;"));
        assert!(d.has_text("t &lt; u"));
        for bad in [
            "<a><b></a></b>",
            "<a>",
            "<a>x & y</a>",
            "<a x=1></a>",
            "<a></a><b></b>",
            "<a>1 < 2</a>",
            "text",
        ] {
            assert!(parse(bad).is_err(), "{bad} should be refused");
        }
    }
}
