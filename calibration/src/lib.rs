//! relight-calibration.
