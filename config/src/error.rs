use std::fmt;
use std::path::PathBuf;

/// One problem with a configuration, naming the key it concerns.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read at all.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The text is not valid TOML, has an unknown key, or a value of the wrong type.
    #[error("{message}")]
    Parse { message: String },
    /// A required key is absent.
    #[error("missing key `{key}`: {hint}")]
    Missing {
        key: &'static str,
        hint: &'static str,
    },
    /// A key has a value outside its allowed range or form.
    #[error("invalid `{key}` = {value}: {reason}")]
    Invalid {
        key: &'static str,
        value: String,
        reason: String,
    },
    /// A directory named by a key does not exist or cannot be used (found by preflight).
    #[error("`{key}` = {}: {reason}", path.display())]
    Directory {
        key: &'static str,
        path: PathBuf,
        reason: String,
    },
}

/// Every problem found in one configuration, in file order, with the file they came from.
#[derive(Debug)]
pub struct ConfigErrors {
    /// The config file, when the config came from one.
    pub path: Option<PathBuf>,
    /// At least one error.
    pub errors: Vec<ConfigError>,
}

impl ConfigErrors {
    pub(crate) fn single(error: ConfigError) -> Self {
        Self {
            path: None,
            errors: vec![error],
        }
    }

    /// Attach the config file the errors came from.
    pub fn with_path(mut self, path: &std::path::Path) -> Self {
        self.path = Some(path.to_path_buf());
        self
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.errors.len();
        match &self.path {
            Some(p) => write!(f, "{}: ", p.display())?,
            None => write!(f, "config: ")?,
        }
        if n > 1 {
            write!(f, "{n} problems: ")?;
        }
        for (i, e) in self.errors.iter().enumerate() {
            if i > 0 {
                write!(f, "; ")?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for ConfigErrors {}

/// Result of loading or validating a configuration.
pub type Result<T> = std::result::Result<T, ConfigErrors>;
