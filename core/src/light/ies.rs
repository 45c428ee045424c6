//! IES LM-63 photometric files (placeholder; the parser lands in its own commit).
