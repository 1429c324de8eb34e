//! Quoting input text in messages. Every reader of choreod that names a token, key, joint or
//! link found in a file goes through [`quote`], so a hostile file cannot turn one error into a
//! line of its own size (a 100 MB BVH token, a 64 KiB `.npy` header, an HDF5 link name) or
//! break it over several lines with control characters.

use std::borrow::Cow;

/// Characters of input text shown in a message; longer text is cut and its length given.
pub const QUOTE_CHARS: usize = 40;

/// `text` in single quotes for a message: at most [`QUOTE_CHARS`] characters, control
/// characters escaped (`\n`, `\u{1b}`), and when cut, `…` and the full length in bytes, e.g.
/// `'aaaaaaaa…' (104857600 bytes)`.
pub fn quote(text: &str) -> String {
    let mut out = String::with_capacity(QUOTE_CHARS + 24);
    out.push('\'');
    let mut chars = text.chars();
    for c in chars.by_ref().take(QUOTE_CHARS) {
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out.push('\'');
    if chars.next().is_some() {
        out.insert(out.len() - 1, '…');
        out.push_str(&format!(" ({} bytes)", text.len()));
    }
    out
}

/// Input text inside a sentence: as it is when short (at most [`QUOTE_CHARS`] characters) and
/// free of control characters, else [`quote`]d. For messages of other parsers that hold input
/// text (TOML's, a config key), where quoting every short key would only add noise.
fn quote_long(text: &str) -> Cow<'_, str> {
    let mut chars = text.chars();
    let short = chars.by_ref().take(QUOTE_CHARS).all(|c| !c.is_control()) && chars.next().is_none();
    if short {
        Cow::Borrowed(text)
    } else {
        Cow::Owned(quote(text))
    }
}

/// Characters of another parser's message kept whole when it does not hold the input text
/// verbatim (TOML's longest, ``unknown field `x`, expected one of`` and a table's keys, stay
/// under it); a longer one is [`quote`]d.
const MESSAGE_CHARS: usize = 400;

/// `message`, another parser's sentence that may hold the input text `found` (e.g. TOML's
/// ``unknown field `…`, expected one of …``), with `found` passed through [`quote_long`]; a
/// message that does not hold it verbatim (escaped on the way) is itself cut when longer than
/// [`MESSAGE_CHARS`].
pub fn quote_inside(message: &str, found: &str) -> String {
    if !found.is_empty() && message.contains(found) {
        message.replace(found, &quote_long(found))
    } else if message.chars().nth(MESSAGE_CHARS).is_none() {
        message.to_string()
    } else {
        quote(message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_text_is_cut_and_its_length_given() {
        assert_eq!(quote("Hips"), "'Hips'");
        assert_eq!(quote(""), "''");
        let exact = "x".repeat(QUOTE_CHARS);
        assert_eq!(quote(&exact), format!("'{exact}'"));
        let long = "y".repeat(100 << 20);
        let q = quote(&long);
        assert_eq!(
            q,
            format!("'{}…' ({} bytes)", "y".repeat(QUOTE_CHARS), 100 << 20)
        );
        // Multi-byte characters are never split.
        let wide = "é".repeat(QUOTE_CHARS + 1);
        assert!(quote(&wide).starts_with(&format!("'{}…'", "é".repeat(QUOTE_CHARS))));
    }

    #[test]
    fn text_inside_a_sentence_is_kept_when_short_and_cut_when_long() {
        assert_eq!(quote_long("paths.inbx"), "paths.inbx");
        assert_eq!(quote_long("a\nb"), "'a\\nb'");
        let key = "k".repeat(1 << 20);
        let message = format!("unknown field `{key}`, expected one of `seed`, `steps`");
        let quoted = quote_inside(&message, &key);
        assert_eq!(
            quoted,
            format!(
                "unknown field `'{}…' (1048576 bytes)`, expected one of `seed`, `steps`",
                "k".repeat(QUOTE_CHARS)
            )
        );
        assert_eq!(quote_inside("expected a value", "x = "), "expected a value");
        assert!(quote_inside(&message, "escaped differently").len() < 100);
    }

    #[test]
    fn control_characters_cannot_start_a_new_line() {
        let q = quote("a\nchoreod: error: FORGED\u{1b}[31m");
        assert!(!q.contains('\n') && !q.contains('\u{1b}'), "{q}");
        assert!(q.starts_with("'a\\nchoreod: error: FORGED\\u{1b}"), "{q}");
    }
}
