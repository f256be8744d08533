//! Cross-crate end-to-end tests live in `tests/`; fixtures in `fixtures/`.
