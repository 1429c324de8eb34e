//! Quoting input text in messages. Every reader of choreod that names a token, key, joint or
//! link found in a file goes through [`quote`], so a hostile file cannot turn one error into a
//! line of its own size (a 100 MB BVH token, a 64 KiB `.npy` header, an HDF5 link name) or
//! break it over several lines with control characters.

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
    fn control_characters_cannot_start_a_new_line() {
        let q = quote("a\nchoreod: error: FORGED\u{1b}[31m");
        assert!(!q.contains('\n') && !q.contains('\u{1b}'), "{q}");
        assert!(q.starts_with("'a\\nchoreod: error: FORGED\\u{1b}"), "{q}");
    }
}
