//! Errors of scene loading: each names the file, the field and what is wrong, on one line.

use std::path::PathBuf;

/// A scene, preset or mesh that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read (the reason is the error's source).
    #[error("{path}: cannot read")]
    Io {
        /// File that failed.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// TOML syntax error or a key of the wrong type or name.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        /// File that failed.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// A value outside its valid range, or keys that do not fit together.
    #[error("{path}: {field}: {message}")]
    Invalid {
        /// File that failed.
        path: PathBuf,
        /// Dotted key, e.g. `gel.poisson_ratio`.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A mesh file that cannot serve as an indenter.
    #[error("{path}: mesh: {message}")]
    Mesh {
        /// Mesh file that failed.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

impl SceneError {
    pub(crate) fn invalid(
        path: &std::path::Path,
        field: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        SceneError::Invalid {
            path: path.to_path_buf(),
            field: field.into(),
            message: message.into(),
        }
    }

    /// A TOML deserialisation error, placed at its line and column in `source`.
    pub(crate) fn from_toml(path: &std::path::Path, source: &str, err: toml::de::Error) -> Self {
        let offset = err.span().map(|s| s.start).unwrap_or(0).min(source.len());
        let before = &source[..offset];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        SceneError::Parse {
            path: path.to_path_buf(),
            line,
            column,
            message: err.message().replace('\n', " ").trim().to_string(),
        }
    }
}
