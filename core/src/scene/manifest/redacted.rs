//! A TOML error as its position and what was wrong, never any of the text: for a file that is
//! no manifest, the text would be its contents.

/// A TOML error as `line L, column C: what` without any of the text: toml's own message
/// quotes the offending line, and serde's quote values (`invalid type: string "…"`) and
/// unknown keys, which for a file that is no manifest would be its contents.
pub(super) fn toml_error(text: &str, mut e: toml::de::Error) -> String {
    let at = e.span().map(|span| {
        let before = &text.as_bytes()[..span.start.min(text.len())];
        let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
        let column = before.iter().rev().take_while(|&&b| b != b'\n').count() + 1;
        format!("line {line}, column {column}: ")
    });
    // Without the input, the message says which key it was in rather than quoting the line.
    e.set_input(None);
    let what = e.to_string().trim_end().replace('\n', " ");
    format!("{}{}", at.unwrap_or_default(), redact(&what))
}

/// `message` with every `"quoted"` literal and the name after `unknown field`/`unknown
/// variant` withheld.
fn redact(message: &str) -> String {
    let mut out = String::with_capacity(message.len());
    let mut rest = message;
    while let Some(i) = rest.find('"') {
        out.push_str(&rest[..i]);
        out.push_str("\"…\"");
        rest = match rest[i + 1..].find('"') {
            Some(j) => &rest[i + 1 + j + 1..],
            None => "",
        };
    }
    out.push_str(rest);
    for lead in ["unknown field `", "unknown variant `"] {
        if let Some(i) = out.find(lead) {
            let start = i + lead.len();
            if let Some(len) = out[start..].find('`') {
                out.replace_range(start..start + len, "…");
            }
        }
    }
    out
}
