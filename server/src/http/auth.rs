//! Admin authentication: a bearer token compared in constant time. Unset in the configuration, a random token
//! is generated once into `<data_dir>/admin-token` (mode 0600) and reused across restarts.

use std::path::Path;

use axum::http::{HeaderMap, header};
use dsrl_service::secrets::{constant_time_eq, load_or_generate_secret};

use crate::error::ApiError;

pub struct AdminAuth {
    token: String,
}

impl AdminAuth {
    pub fn new(token: String) -> Self {
        AdminAuth { token }
    }

    /// The configured token, or the one stored in (or newly generated into) `token_file`.
    pub fn load_or_create(configured: Option<&str>, token_file: &Path) -> anyhow::Result<AdminAuth> {
        if let Some(token) = configured {
            anyhow::ensure!(token.len() >= 16, "auth.admin_token must have at least 16 characters");
            return Ok(AdminAuth::new(token.to_owned()));
        }
        Ok(AdminAuth::new(load_or_generate_secret(token_file, "admin token")?))
    }

    pub fn check(&self, headers: &HeaderMap) -> Result<(), ApiError> {
        let value = headers.get(header::AUTHORIZATION).ok_or(ApiError::Unauthenticated)?;
        let presented = value
            .to_str()
            .ok()
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim)
            .ok_or(ApiError::Unauthenticated)?;
        if constant_time_eq(presented.as_bytes(), self.token.as_bytes()) {
            Ok(())
        } else {
            Err(ApiError::PermissionDenied)
        }
    }
}

/// Whether a request comes with a token this server knows (the admin's, or a leaderboard user's): only requests
/// without one are held to the anonymous budget of derived data.
pub async fn requester(state: &crate::AppState, headers: &HeaderMap) -> crate::datasets::service::Requester {
    use crate::datasets::service::Requester;
    if dsrl_service::secrets::bearer(headers).is_none() {
        return Requester::Anonymous;
    }
    if state.auth.check(headers).is_ok()
        || dsrl_leaderboard::users::authenticate(&state.leaderboard.db, headers)
            .await
            .is_ok()
    {
        Requester::Authenticated
    } else {
        Requester::Anonymous
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(value: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(header::AUTHORIZATION, value.parse().unwrap());
        h
    }

    #[test]
    fn bearer_tokens_are_checked() {
        let auth = AdminAuth::new("s3cret-token-0123".into());
        assert!(auth.check(&headers("Bearer s3cret-token-0123")).is_ok());
        assert!(matches!(auth.check(&HeaderMap::new()), Err(ApiError::Unauthenticated)));
        assert!(matches!(
            auth.check(&headers("Basic abc")),
            Err(ApiError::Unauthenticated)
        ));
        assert!(matches!(
            auth.check(&headers("Bearer wrong")),
            Err(ApiError::PermissionDenied)
        ));
    }

    #[test]
    fn generated_tokens_persist_with_private_permissions() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("admin-token");
        let a = AdminAuth::load_or_create(None, &path).unwrap();
        let b = AdminAuth::load_or_create(None, &path).unwrap();
        assert_eq!(a.token, b.token);
        assert_eq!(a.token.len(), 64);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&path).unwrap().permissions().mode() & 0o777, 0o600);
        }
        assert!(AdminAuth::load_or_create(Some("short"), &path).is_err());
    }
}
