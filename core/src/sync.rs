//! Timestamp synchroniser.
