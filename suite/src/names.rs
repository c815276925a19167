//! The names users and leaderboard entries may take: checked by the server, and by `dsrl-train --submit` and the
//! CLI before any work, with the same rule.

/// Names a user or an entry may not take, nor anything that reads the same (`reads_as`): the board's own rows
/// (`paper`), the reference account, and the service itself.
pub const RESERVED_NAMES: &[&str] = &["paper", "dsrl", "dsrl-reference", "admin"];

/// User and entry names: 1–64 letters, digits, `.`, `_`, `-`; not only dots (a browser resolves `/users/..` to
/// `/`); not starting with `-` or `.`, so no spreadsheet reads an exported name as a formula (`-A1-B1`) and no
/// path reads it as relative; and nothing that reads as a reserved name (`Paper`, `dsrl_reference`, `p4per`).
pub fn check_name(kind: &str, name: &str) -> Result<(), String> {
    let charset = !name.is_empty()
        && name.len() <= 64
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if !charset {
        return Err(format!("{kind} {name:?}: use 1 to 64 letters, digits, '.', '_' or '-'"));
    }
    if name.starts_with(['-', '.']) {
        return Err(format!(
            "{kind} {name:?}: start with a letter, a digit or '_' (a leading '-' reads as a formula in a \
             spreadsheet, a leading '.' as a relative path)"
        ));
    }
    if let Some(reserved) = RESERVED_NAMES.iter().find(|r| reads_as(name) == reads_as(r)) {
        return Err(format!(
            "{kind} {name:?} reads as the reserved name {reserved:?}; choose another"
        ));
    }
    Ok(())
}

/// A name's skeleton: lowercase, separators dropped, digits that pass for letters replaced (`P4-per` → `paper`).
/// Two names with one skeleton read as the same name.
fn reads_as(name: &str) -> String {
    name.chars()
        .filter(|c| !matches!(c, '.' | '_' | '-'))
        .map(|c| match c.to_ascii_lowercase() {
            '0' => 'o',
            '1' => 'l',
            '3' => 'e',
            '4' => 'a',
            '5' => 's',
            '7' => 't',
            c => c,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_that_read_as_formulas_paths_or_reserved_names_are_refused() {
        for ok in ["alice", "bc_safe-seed.2", "_x", "Team42", "paperclip", "a.b"] {
            assert!(check_name("user name", ok).is_ok(), "{ok}");
        }
        for (bad, why) in [
            ("", "1 to 64"),
            (".", "start with"),
            ("..", "start with"),
            ("-A1-B1", "formula"),
            (".hidden", "relative path"),
            ("a b", "1 to 64"),
            ("=1+1", "1 to 64"),
            ("Paper", "reserved name \"paper\""),
            ("p4per", "reserved name \"paper\""),
            ("dsrl_reference", "reserved name \"dsrl-reference\""),
            ("DSRL.Reference", "reserved name \"dsrl-reference\""),
            ("ADMIN", "reserved name \"admin\""),
        ] {
            let err = check_name("user name", bad).unwrap_err().to_string();
            assert!(err.contains(why), "{bad:?}: {err}");
        }
        assert!(check_name("user name", &"a".repeat(64)).is_ok());
        assert!(check_name("user name", &"a".repeat(65)).is_err());
    }
}
