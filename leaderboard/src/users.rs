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

/// User and entry names: the rule of `dsrl_suite::names`, as the API's error.
pub fn check_name(kind: &str, name: &str) -> Result<(), ApiError> {
    dsrl_suite::names::check_name(kind, name).map_err(ApiError::InvalidArgument)
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
