//! Typed identifiers: a task id, a dataset version id (sha256 of the Parquet bytes) and a movable tag name.
//! Parsing them once at the edge means the rest of the code never handles an unchecked string.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdError {
    #[error("invalid task id {0:?}: expected letters, digits, '-', '_' or '.', at most 128 characters")]
    Task(String),
    #[error("invalid version id {0:?}: expected the 64 hex digits of a sha256")]
    Version(String),
    #[error("invalid tag {0:?}: expected 1-64 lowercase letters, digits, '-', '_' or '.', starting with a letter")]
    Tag(String),
}

/// An offline task id as DSRL registers it, e.g. `OfflineAntRun-v0`. Syntax only; the catalog says if it exists.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct TaskId(String);

impl TaskId {
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl FromStr for TaskId {
    type Err = IdError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let ok = !s.is_empty()
            && s.len() <= 128
            && s.bytes()
                .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'));
        if ok {
            Ok(TaskId(s.to_owned()))
        } else {
            Err(IdError::Task(s.to_owned()))
        }
    }
}

/// The first 12 digits of a hex digest or commit, the form people read in logs, tables and pages. A shorter
/// string comes back whole rather than panicking: these are for display, and their inputs are not all checked.
pub fn short_hex(hex: &str) -> &str {
    hex.get(..12).unwrap_or(hex)
}

/// A dataset version: the lowercase hex sha256 of the version's Parquet bytes. Content-addressed, so immutable.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct VersionId(String);

impl VersionId {
    pub fn from_digest(digest: &[u8; 32]) -> Self {
        VersionId(hex::encode(digest))
    }
    pub fn as_str(&self) -> &str {
        &self.0
    }
    /// The first 12 hex digits, for tables meant for people.
    pub fn short(&self) -> &str {
        short_hex(&self.0)
    }
    fn looks_like(s: &str) -> bool {
        s.len() == 64 && s.bytes().all(|b| b.is_ascii_hexdigit())
    }
}

impl FromStr for VersionId {
    type Err = IdError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if Self::looks_like(s) {
            Ok(VersionId(s.to_ascii_lowercase()))
        } else {
            Err(IdError::Version(s.to_owned()))
        }
    }
}

/// A movable name for a version of one task's dataset: `latest`, or a named release such as `paper-v1`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct TagName(String);

impl TagName {
    pub const LATEST: &'static str = "latest";
    /// The committed starter dataset a server loads at start-up.
    pub const STARTER: &'static str = "starter";
    /// A full build (`dsrl-admin build`): the task's dataset at the paper's size.
    pub const FULL: &'static str = "full";

    pub fn latest() -> Self {
        TagName(Self::LATEST.to_owned())
    }

    pub fn starter() -> Self {
        TagName(Self::STARTER.to_owned())
    }
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl FromStr for TagName {
    type Err = IdError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let ok = !s.is_empty()
            && s.len() <= 64
            && s.as_bytes()[0].is_ascii_lowercase()
            && s.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || matches!(b, b'-' | b'_' | b'.'))
            // A 64-hex-digit tag would be ambiguous with a version id.
            && !VersionId::looks_like(s);
        if ok {
            Ok(TagName(s.to_owned()))
        } else {
            Err(IdError::Tag(s.to_owned()))
        }
    }
}

/// How a request names a version: by its id, or by a tag that currently points at one.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum VersionRef {
    Version(VersionId),
    Tag(TagName),
}

impl FromStr for VersionRef {
    type Err = IdError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if VersionId::looks_like(s) {
            s.parse().map(VersionRef::Version)
        } else {
            s.parse().map(VersionRef::Tag)
        }
    }
}

macro_rules! string_id {
    ($($t:ty),*) => {$(
        impl fmt::Display for $t {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(&self.0)
            }
        }
        impl TryFrom<String> for $t {
            type Error = IdError;
            fn try_from(s: String) -> Result<Self, Self::Error> {
                s.parse()
            }
        }
        impl From<$t> for String {
            fn from(id: $t) -> String {
                id.0
            }
        }
    )*};
}
string_id!(TaskId, VersionId, TagName);

impl fmt::Display for VersionRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            VersionRef::Version(v) => v.fmt(f),
            VersionRef::Tag(t) => t.fmt(f),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn version_ids_are_normalized_to_lowercase() {
        let upper = "AB".repeat(32);
        let v: VersionId = upper.parse().unwrap();
        assert_eq!(v.as_str(), "ab".repeat(32));
        assert_eq!(v.short(), "abababababab");
        assert!("abc".parse::<VersionId>().is_err());
        assert!("g".repeat(64).parse::<VersionId>().is_err());
    }

    #[test]
    fn short_hex_takes_twelve_digits_and_keeps_shorter_strings_whole() {
        assert_eq!(short_hex(&"0123456789ab".repeat(5)), "0123456789ab");
        assert_eq!(short_hex("abc"), "abc");
        assert_eq!(short_hex(""), "");
    }

    #[test]
    fn refs_distinguish_versions_from_tags() {
        assert_eq!(
            "latest".parse::<VersionRef>().unwrap(),
            VersionRef::Tag(TagName::latest())
        );
        assert!(matches!(
            "0".repeat(64).parse::<VersionRef>().unwrap(),
            VersionRef::Version(_)
        ));
        assert!("Latest".parse::<VersionRef>().is_err());
        assert!("../etc".parse::<VersionRef>().is_err());
        assert!("paper-v1.2".parse::<TagName>().is_ok());
        assert!("1abc".parse::<TagName>().is_err());
    }

    #[test]
    fn task_ids_reject_path_characters() {
        assert!("OfflineAntRun-v0".parse::<TaskId>().is_ok());
        assert!("a/b".parse::<TaskId>().is_err());
        assert!("".parse::<TaskId>().is_err());
        let json = serde_json::to_string(&"OfflineAntRun-v0".parse::<TaskId>().unwrap()).unwrap();
        assert_eq!(json, "\"OfflineAntRun-v0\"");
        assert!(serde_json::from_str::<TaskId>("\"x y\"").is_err());
    }
}
