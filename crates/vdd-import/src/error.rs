//! The importers' error type.

use std::path::PathBuf;

/// Errors from reading a package's files, building an imported teacher and running it.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// Reading or writing a file failed.
    #[error("i/o error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A JSON file does not parse.
    #[error("{path} is not valid JSON: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// A key the importer needs is absent.
    #[error("{file}: missing key `{key}`")]
    MissingKey {
        /// The file (or the part of it) searched.
        file: String,
        /// The key.
        key: String,
    },
    /// A value is malformed, out of range or of a layout this importer does not support.
    #[error("{file}: `{key}` = {value} is not supported")]
    BadValue {
        /// The file (or the part of it).
        file: String,
        /// The key.
        key: String,
        /// The offending value.
        value: String,
    },
    /// An external converter (`scripts/import/*.py`) ran and failed.
    #[error("{} failed on {} ({status})", .script.display(), .input.display())]
    Converter {
        /// The script.
        script: PathBuf,
        /// The file it converted.
        input: PathBuf,
        /// Its exit status.
        status: String,
    },
    /// Building or loading a network failed (a missing tensor names its key).
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// A runtime check of the core vocabulary failed.
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
}

impl ImportError {
    /// A [`ImportError::MissingKey`].
    pub fn missing(file: impl Into<String>, key: impl Into<String>) -> Self {
        Self::MissingKey { file: file.into(), key: key.into() }
    }

    /// A [`ImportError::BadValue`].
    pub fn bad(file: impl Into<String>, key: impl Into<String>, value: impl ToString) -> Self {
        Self::BadValue { file: file.into(), key: key.into(), value: value.to_string() }
    }
}

impl From<ImportError> for vdd_core::CoreError {
    fn from(e: ImportError) -> Self {
        match e {
            ImportError::Core(c) => c,
            other => vdd_core::CoreError::implementor(other),
        }
    }
}
