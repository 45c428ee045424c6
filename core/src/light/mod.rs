//! Light sources with angular intensity distributions (Nishita et al. 1987,
//! appendix) and IES LM-63 photometry.

pub mod ies;
