//! Sun and sky: Klassen's spectral sun and sky over a spherical earth with a
//! haze shell (`klassen`), and a layered exponential atmosphere with ozone and
//! twilight (`atmosphere`). World textures and sun-lamp values are built on
//! these (see `docs/models.md`).

pub mod atmosphere;
pub mod klassen;
pub mod texture;
