use std::fmt;
use std::path::PathBuf;

/// One problem with a configuration, naming the key it concerns.
///
/// Variants carry input text raw (a key or value of the file, TOML's message quoting the file):
/// [`ConfigErrors::describe`] passes it through the caller's quoting function, so a hostile or
/// mistaken 1 MB key gives a short line. `Display` shows it unchanged.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read at all.
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The text is not valid TOML, has an unknown key, or a value of the wrong type.
    Parse {
        /// Line of the error in the file, when TOML gives its place.
        line: Option<usize>,
        /// The key (`table.key`) on that line, as written.
        key: Option<String>,
        /// TOML's message (it may hold `found`).
        message: String,
        /// The file's text at the error (a key or value), as written.
        found: Option<String>,
    },
    /// A required key is absent.
    Missing {
        key: &'static str,
        hint: &'static str,
    },
    /// A key has a value outside its allowed range or form (`value` as written, strings in
    /// double quotes).
    Invalid {
        key: &'static str,
        value: String,
        reason: String,
    },
    /// A directory named by a key does not exist or cannot be used (found by preflight).
    Directory {
        key: &'static str,
        path: PathBuf,
        reason: String,
    },
}

/// How input text is shown in a message (see [`ConfigErrors::describe`]): `quote(message,
/// found)` is `message` (a key or value itself, or TOML's sentence) with the input text
/// `found` it holds shown as the caller wants.
pub type Quote<'q> = &'q dyn Fn(&str, &str) -> String;

impl ConfigError {
    fn describe(&self, quote: Quote<'_>) -> String {
        match self {
            Self::Read { path, source } => format!("cannot read {}: {source}", path.display()),
            Self::Parse {
                line,
                key,
                message,
                found,
            } => {
                let message = quote(message, found.as_deref().unwrap_or_default());
                match (line, key) {
                    (Some(line), Some(key)) => {
                        format!("line {line}, key `{}`: {message}", quote(key, key))
                    }
                    (Some(line), None) => format!("line {line}: {message}"),
                    (None, _) => message,
                }
            }
            Self::Missing { key, hint } => format!("missing key `{key}`: {hint}"),
            Self::Invalid { key, value, reason } => {
                // The reason may repeat the value (a parser's message about it).
                let reason = quote(reason, value);
                format!("invalid `{key}` = {}: {reason}", quote(value, value))
            }
            Self::Directory { key, path, reason } => {
                let path = path.to_string_lossy();
                format!("`{key}` = {}: {reason}", quote(&path, &path))
            }
        }
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.describe(&unchanged))
    }
}

/// Input text as it is (`Display`).
fn unchanged(message: &str, _found: &str) -> String {
    message.to_string()
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

impl ConfigErrors {
    /// Every error on one line, the input text they hold (keys, values, the file's text in
    /// TOML's messages, folder names) passed through `quote`. The binary passes
    /// `choreo_dsp::quote_inside`, which cuts long text (this crate sits beside dsp, not above
    /// it, so the cutting happens at the edge); `Display` passes text unchanged.
    pub fn describe(&self, quote: Quote<'_>) -> String {
        let mut line = match &self.path {
            Some(p) => format!("{}: ", p.display()),
            None => "config: ".to_string(),
        };
        if self.errors.len() > 1 {
            line.push_str(&format!("{} problems: ", self.errors.len()));
        }
        let errors: Vec<String> = self.errors.iter().map(|e| e.describe(quote)).collect();
        line.push_str(&errors.join("; "));
        line
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.describe(&unchanged))
    }
}

impl std::error::Error for ConfigErrors {}

/// Result of loading or validating a configuration.
pub type Result<T> = std::result::Result<T, ConfigErrors>;
