//! What the benchmarks share to read and write files: atomic writes, TOML configs whose errors
//! name their line, and the charts' bundled font.

use std::path::Path;

use plotters::style::FontStyle;

use crate::Error;

/// The bundled DejaVu Sans, registered as the charts' [`SANS`].
const FONT: &[u8] = include_bytes!("../../../assets/fonts/DejaVuSans.ttf");

/// The family name the charts and figures draw their text in.
pub(crate) const SANS: &str = "sans-serif";

/// Writes `bytes` to `path` (its directory created) through [`sparsh_data::write_atomic`]; a
/// failure names the file once, with its cause.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| Error::file(dir, e))?;
    }
    sparsh_data::write_atomic(path, bytes).map_err(|e| match std::error::Error::source(&e) {
        Some(cause) => Error::file(path, cause),
        None => Error::File {
            path: path.display().to_string(),
            msg: e.to_string(),
        },
    })
}

/// Reads a TOML file into `T`; a syntax error or unknown key names the file and its line.
pub(crate) fn read_toml<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, Error> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
    toml::from_str(&text).map_err(|e| {
        let msg = e.message().to_string();
        match e.span() {
            Some(span) => {
                let line = text[..span.start].lines().count().max(1);
                Error::file(path, format!("line {line}: {msg}"))
            }
            None => Error::file(path, msg),
        }
    })
}

/// Registers the bundled DejaVu Sans as the charts' `sans-serif`.
pub(crate) fn register_sans() -> Result<(), Error> {
    plotters::style::register_font(SANS, FontStyle::Normal, FONT)
        .map_err(|_| Error::file("assets/fonts/DejaVuSans.ttf", "not a usable font"))
}
