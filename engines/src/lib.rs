//! relight-engines.
