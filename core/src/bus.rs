//! Typed frame bus.
