//! Light types shared by estimators and engines.
