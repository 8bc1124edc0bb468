//! Configuration by name: a built-in text compiled into the binary, or a TOML file by path.

use std::borrow::Cow;

use thiserror::Error;

#[derive(Debug, Error)]
pub enum SourceError {
    #[error("unknown {kind} '{name}': not a built-in ({builtins}) and no such file")]
    Unknown {
        kind: &'static str,
        name: String,
        builtins: String,
    },
    #[error("cannot read {kind} file {path}: {source}")]
    Read {
        kind: &'static str,
        path: String,
        source: std::io::Error,
    },
}

/// The text of the built-in `name`, or of the file at `name`.
pub fn builtin_or_file(
    kind: &'static str,
    name: &str,
    builtins: &'static [(&'static str, &'static str)],
) -> Result<Cow<'static, str>, SourceError> {
    if let Some((_, text)) = builtins.iter().find(|(n, _)| *n == name) {
        return Ok(Cow::Borrowed(text));
    }
    let path = std::path::Path::new(name);
    if !path.exists() {
        return Err(SourceError::Unknown {
            kind,
            name: name.to_string(),
            builtins: builtins
                .iter()
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(", "),
        });
    }
    std::fs::read_to_string(path)
        .map(Cow::Owned)
        .map_err(|source| SourceError::Read {
            kind,
            path: name.to_string(),
            source,
        })
}
