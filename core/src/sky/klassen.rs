//! Klassen 1987 sun and sky model (work in progress).
