//! Users who submit: an admin creates one and gets its bearer token once; only the token's sha256 is stored.

use axum::http::HeaderMap;
use serde::Serialize;
use sha2::{Digest, Sha256};
use sqlx::Row;

use dsrl_service::db::Db;
use dsrl_service::db::now_rfc3339;
use dsrl_service::error::ApiError;
use dsrl_service::secrets::{bearer, random_hex};

#[derive(Debug, Clone, Serialize)]
pub struct User {
    pub id: i64,
    pub name: String,
}

/// A user just created, with the only copy of its token.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct NewUser {
    pub id: i64,
    pub name: String,
    pub token: String,
}

fn token_digest(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

/// Names a user or an entry may not take, nor anything that reads the same (`reads_as`): the board's own rows
/// (`paper`), the reference account, and the service itself.
pub const RESERVED_NAMES: &[&str] = &["paper", "dsrl", "dsrl-reference", "admin"];

/// User and entry names: 1–64 letters, digits, `.`, `_`, `-`; not only dots (a browser resolves `/users/..` to
/// `/`); not starting with `-` or `.`, so no spreadsheet reads an exported name as a formula (`-A1-B1`) and no
/// path reads it as relative; and nothing that reads as a reserved name (`Paper`, `dsrl_reference`, `p4per`).
pub fn check_name(kind: &str, name: &str) -> Result<(), ApiError> {
    let charset = !name.is_empty()
        && name.len() <= 64
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if !charset {
        return Err(ApiError::InvalidArgument(format!(
            "{kind} {name:?}: use 1 to 64 letters, digits, '.', '_' or '-'"
        )));
    }
    if name.starts_with(['-', '.']) {
        return Err(ApiError::InvalidArgument(format!(
            "{kind} {name:?}: start with a letter, a digit or '_' (a leading '-' reads as a formula in a \
             spreadsheet, a leading '.' as a relative path)"
        )));
    }
    if let Some(reserved) = RESERVED_NAMES.iter().find(|r| reads_as(name) == reads_as(r)) {
        return Err(ApiError::InvalidArgument(format!(
            "{kind} {name:?} reads as the reserved name {reserved:?}; choose another"
        )));
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

pub async fn create(db: &Db, name: &str) -> Result<NewUser, ApiError> {
    check_name("user name", name)?;
    let token = format!("dsrl_{}", random_hex().map_err(ApiError::internal)?);
    // In an explicit transaction whose commit is checked: in autocommit, SQLite hands the RETURNING row over before
    // the statement's implicit commit, and a commit that then fails (an unwritable file) was never seen, so the
    // caller got a token for a user that does not exist.
    let mut tx = db.begin().await?;
    let row = sqlx::query(
        "INSERT INTO users (name, token_sha256, created_at) VALUES ($1, $2, $3) ON CONFLICT (name) DO NOTHING
         RETURNING id",
    )
    .bind(name)
    .bind(token_digest(&token))
    .bind(now_rfc3339())
    .fetch_optional(&mut *tx)
    .await?;
    let Some(row) = row else {
        return Err(ApiError::AlreadyExists(format!("a user named {name} exists")));
    };
    let id = row.try_get(0)?;
    tx.commit().await?;
    Ok(NewUser {
        id,
        name: name.to_owned(),
        token,
    })
}

/// The user whose token the request carries.
pub async fn authenticate(db: &Db, headers: &HeaderMap) -> Result<User, ApiError> {
    let token = bearer(headers).ok_or(ApiError::UserUnauthenticated)?;
    let row = sqlx::query("SELECT id, name FROM users WHERE token_sha256 = $1")
        .bind(token_digest(token))
        .fetch_optional(db.pool())
        .await?
        .ok_or(ApiError::UnknownUserToken)?;
    Ok(User {
        id: row.try_get(0)?,
        name: row.try_get(1)?,
    })
}

/// The account that holds the imported reference entries. Its name has a space, which `check_name` refuses, so no
/// user created through the API can take it; its token is a random value nobody is given, so nobody can submit as
/// it.
pub const REFERENCE_USER: &str = "dsrl reference";

/// The reference account's id, created on first use.
pub async fn reference_user(db: &Db) -> Result<i64, ApiError> {
    let token = random_hex().map_err(ApiError::internal)?;
    sqlx::query("INSERT INTO users (name, token_sha256, created_at) VALUES ($1, $2, $3) ON CONFLICT (name) DO NOTHING")
        .bind(REFERENCE_USER)
        .bind(token_digest(&token))
        .bind(now_rfc3339())
        .execute(db.pool())
        .await?;
    let row = sqlx::query("SELECT id FROM users WHERE name = $1")
        .bind(REFERENCE_USER)
        .fetch_one(db.pool())
        .await?;
    Ok(row.try_get(0)?)
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
