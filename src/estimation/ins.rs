//! Strapdown INS (being written).
