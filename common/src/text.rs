//! Text from files as error messages show it.

/// File content as an error message shows it: control and invisible characters escaped (a NUL, a terminal
/// escape or a byte-order mark must not reach the terminal raw or hide), at most `max` characters (a
/// hostile field may be megabytes).
pub fn shown(text: &str, max: usize) -> String {
    let mut out = String::new();
    for (k, c) in text.chars().enumerate() {
        if k == max {
            out.push_str(&format!("... ({} characters)", text.chars().count()));
            break;
        }
        let invisible =
            matches!(c, '\u{200b}'..='\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}' | '\u{feff}');
        if c.is_control() || invisible {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::shown;

    #[test]
    fn control_and_invisible_characters_are_escaped_and_long_text_cut() {
        assert_eq!(shown("a\0b\x1b[31m\u{feff}", 40), "a\\u{0}b\\u{1b}[31m\\u{feff}");
        assert_eq!(shown("résumé", 40), "résumé");
        assert_eq!(shown(&"x".repeat(100), 3), "xxx... (100 characters)");
    }
}
