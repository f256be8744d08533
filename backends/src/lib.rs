//! relight-backends.
