//! L2 spherical harmonics (9 coefficients per colour channel).
