//! The one way moonhaul reads a TOML settings file (`configs/*.toml`), for every crate and
//! binary: size-capped read ([`crate::input`]), strict parse, then the file's own range and
//! cross-field checks. Every error names the file and the dotted path of the field at fault
//! (`physics.control_hz`, `arm[7]`).
//!
//! Rules every config type follows:
//! - `#[serde(deny_unknown_fields)]` on every struct and **every key required**: no serde
//!   defaults, so a typo or a forgotten key is an error, never a silent fallback, and the
//!   shipped file under `configs/` is the one source of each number (its comments say which
//!   values are the paper's).
//! - Fixed-size arrays go through [`exact_array`], which rejects a wrong number of entries
//!   (serde's own array support silently drops extra ones).
//! - [`Validate`] checks every numeric field: finite, in range, and with an upper bound that
//!   keeps the program from hanging or exhausting memory; plus the cross-field rules.

use std::path::{Path, PathBuf};

use serde::de::{DeserializeOwned, Error as _};
use serde::{Deserialize, Deserializer};

use crate::input::{self, InputError};

/// A config value that fails its check: the dotted path of the field and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("field `{field}`: {reason}")]
pub struct FieldError {
    pub field: String,
    pub reason: String,
}

impl FieldError {
    pub fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        FieldError {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// The same error seen from the enclosing section: `within("physics")` turns
    /// `control_hz` into `physics.control_hz`.
    pub fn within(mut self, section: &str) -> Self {
        self.field = if self.field.starts_with('[') {
            format!("{section}{}", self.field)
        } else {
            format!("{section}.{}", self.field)
        };
        self
    }
}

/// Runs a section's checks and prefixes any error with the section's name. A closure, so the
/// checks' own `?` stays inside the section.
pub fn section(
    name: &str,
    checks: impl FnOnce() -> Result<(), FieldError>,
) -> Result<(), FieldError> {
    checks().map_err(|e| e.within(name))
}

/// A settings type that checks its own values after parsing.
pub trait Validate {
    /// Completes the value from what the file refers to, before it is validated: relative
    /// paths resolved against the file's folder, referenced config files loaded. Nothing by
    /// default.
    fn resolve(&mut self, _config_path: &Path) -> Result<(), ConfigError> {
        Ok(())
    }

    /// The first invalid field, if any, with its path relative to this value.
    fn validate(&self) -> Result<(), FieldError>;
}

/// Why a settings file cannot be used. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error("{}: {}{message}", path.display(), field_prefix(field))]
    Parse {
        path: PathBuf,
        /// Dotted path of the field the parser stopped at (empty for syntax errors).
        field: String,
        message: String,
    },
    // The field error is part of the message, not a `source`, so a chain prints it once.
    #[error("{}: {error}", path.display())]
    Invalid { path: PathBuf, error: FieldError },
}

fn field_prefix(field: &str) -> String {
    if field.is_empty() || field == "." {
        String::new()
    } else {
        format!("field `{field}`: ")
    }
}

impl ConfigError {
    /// The dotted path of the field at fault, when one is known.
    pub fn field(&self) -> Option<&str> {
        match self {
            ConfigError::Parse { field, .. } if !field.is_empty() => Some(field),
            ConfigError::Invalid { error, .. } => Some(&error.field),
            _ => None,
        }
    }
}

/// Reads, parses and validates a TOML settings file (at most [`input::MAX_CONFIG_BYTES`]).
pub fn load<T: DeserializeOwned + Validate>(path: &Path) -> Result<T, ConfigError> {
    let text = input::read_capped_text(path, input::MAX_CONFIG_BYTES)?;
    parse(&text, path)
}

/// Parses and validates TOML text; `path` names the source in errors.
pub fn parse<T: DeserializeOwned + Validate>(text: &str, path: &Path) -> Result<T, ConfigError> {
    let parse_error = |field: String, error: toml::de::Error| ConfigError::Parse {
        path: path.to_owned(),
        field,
        message: error.to_string().trim_end().to_owned(),
    };
    let deserializer =
        toml::Deserializer::parse(text).map_err(|e| parse_error(String::new(), e))?;
    let mut value: T = serde_path_to_error::deserialize(deserializer).map_err(|e| {
        let field = e.path().to_string();
        parse_error(field, e.into_inner())
    })?;
    value.resolve(path)?;
    value.validate().map_err(|error| ConfigError::Invalid {
        path: path.to_owned(),
        error,
    })?;
    Ok(value)
}

/// A path given in a config file, resolved against the file's folder when relative.
pub fn resolve(config_path: &Path, given: &Path) -> PathBuf {
    if given.is_relative() {
        config_path.parent().unwrap_or(Path::new(".")).join(given)
    } else {
        given.to_owned()
    }
}

/// `configs/control.toml`: the control rate of every unit, the one source of it. The
/// simulator's, the unit daemon's and the CAN drives' configs name this file (`control =
/// "control.toml"`) instead of repeating the number.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlConfig {
    /// Control ticks per second, Hz (paper: 50).
    pub control_rate_hz: f64,
}

impl Validate for ControlConfig {
    /// 1 Hz to 1 kHz: a CiA 402 SYNC cycle of nine drives on one 1 Mbit/s bus needs ~0.5 ms.
    fn validate(&self) -> Result<(), FieldError> {
        in_range("control_rate_hz", self.control_rate_hz, 1.0, 1000.0)
    }
}

impl ControlConfig {
    /// One control period, s.
    pub fn period_s(&self) -> f64 {
        1.0 / self.control_rate_hz
    }

    /// Loads the control config a settings file at `config_path` names as `given`; errors
    /// name the referenced file (and its field).
    pub fn load_referenced(config_path: &Path, given: &Path) -> Result<Self, ConfigError> {
        load(&resolve(config_path, given))
    }
}

/// A file of this source tree by its path from the repository root (`configs/sim.toml`), for
/// tests, benches and tools that run from a checkout. Never used on a robot.
pub fn repo_file(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(relative)
}

/// `#[serde(deserialize_with = "exact_array")]` for `[T; N]` fields: exactly N entries.
pub fn exact_array<'de, D, T, const N: usize>(deserializer: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    let entries: Vec<T> = Vec::deserialize(deserializer)?;
    let len = entries.len();
    entries
        .try_into()
        .map_err(|_| D::Error::invalid_length(len, &format!("exactly {N} entries").as_str()))
}

/// Finite and within `[min, max]`.
pub fn in_range(field: &str, value: f64, min: f64, max: f64) -> Result<(), FieldError> {
    if value.is_finite() && (min..=max).contains(&value) {
        Ok(())
    } else {
        Err(FieldError::new(
            field,
            format!("{value:?} must be finite and in [{min:?}, {max:?}]"),
        ))
    }
}

/// Finite, above zero and at most `max`.
pub fn positive(field: &str, value: f64, max: f64) -> Result<(), FieldError> {
    if value.is_finite() && value > 0.0 && value <= max {
        Ok(())
    } else {
        Err(FieldError::new(
            field,
            format!("{value:?} must be finite and in (0, {max:?}]"),
        ))
    }
}

/// An integer within `[min, max]`.
pub fn count(field: &str, value: u64, min: u64, max: u64) -> Result<(), FieldError> {
    if (min..=max).contains(&value) {
        Ok(())
    } else {
        Err(FieldError::new(
            field,
            format!("{value} must be in [{min}, {max}]"),
        ))
    }
}

/// A `[low, high]` range with `min <= low <= high <= max`, both finite.
pub fn interval(field: &str, [low, high]: [f64; 2], min: f64, max: f64) -> Result<(), FieldError> {
    if low.is_finite() && high.is_finite() && min <= low && low <= high && high <= max {
        Ok(())
    } else {
        Err(FieldError::new(
            field,
            format!("[{low:?}, {high:?}] must satisfy {min:?} <= low <= high <= {max:?}"),
        ))
    }
}

/// `rate / base` as a whole number, or an error naming `field` (a rate must divide another).
pub fn integer_ratio(field: &str, rate: f64, base: f64) -> Result<usize, FieldError> {
    let r = rate / base;
    let rounded = r.round();
    if r.is_finite() && rounded >= 1.0 && rounded <= u32::MAX as f64 && (r - rounded).abs() < 1e-9 {
        Ok(rounded as usize)
    } else {
        Err(FieldError::new(
            field,
            format!("{rate:?} / {base:?} = {r:?} is not a whole number >= 1"),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Demo {
        rate_hz: f64,
        inner: Inner,
    }

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Inner {
        #[serde(deserialize_with = "exact_array")]
        pair: [f64; 2],
        count: u32,
    }

    impl Validate for Demo {
        fn validate(&self) -> Result<(), FieldError> {
            positive("rate_hz", self.rate_hz, 1000.0)?;
            section("inner", || {
                interval("pair", self.inner.pair, 0.0, 1.0)?;
                count("count", self.inner.count.into(), 1, 10)
            })
        }
    }

    fn error(text: &str) -> ConfigError {
        parse::<Demo>(text, Path::new("demo.toml")).unwrap_err()
    }

    #[test]
    fn every_class_of_bad_value_names_file_and_field() {
        let good = "rate_hz = 50.0\n[inner]\npair = [0.2, 0.4]\ncount = 3\n";
        parse::<Demo>(good, Path::new("demo.toml")).unwrap();
        let cases = [
            (good.replace("50.0", "nan"), "rate_hz"),
            (good.replace("50.0", "inf"), "rate_hz"),
            (good.replace("50.0", "-1.0"), "rate_hz"),
            (good.replace("50.0", "1e9"), "rate_hz"),
            (good.replace("[0.2, 0.4]", "[0.2, 0.4, 0.6]"), "inner.pair"),
            (good.replace("[0.2, 0.4]", "[0.2]"), "inner.pair"),
            (good.replace("[0.2, 0.4]", "[0.4, 0.2]"), "inner.pair"),
            (good.replace("count = 3", "count = 11"), "inner.count"),
            (good.replace("count = 3", "count = -1"), "inner.count"),
            (good.replace("count = 3", "count = 3\nextra = 1"), "inner"),
            (good.replace("count = 3\n", ""), "inner"),
            (good.replace("rate_hz", "rate_hertz"), "rate_hertz"),
        ];
        for (text, field) in cases {
            let e = error(&text);
            let message = e.to_string();
            assert!(
                message.starts_with("demo.toml") && message.contains(field),
                "{field}: {message}"
            );
        }
        assert_eq!(
            error(&good.replace("count = 3", "count = 11")).field(),
            Some("inner.count")
        );
        let syntax = error("rate_hz = = 1");
        assert!(syntax.to_string().starts_with("demo.toml: "), "{syntax}");
    }

    #[test]
    fn load_caps_the_file_and_names_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("huge.toml");
        let line = "# padding padding padding padding padding padding padding padding\n";
        std::fs::write(
            &path,
            line.repeat(input::MAX_CONFIG_BYTES as usize / line.len() + 1),
        )
        .unwrap();
        let e = load::<Demo>(&path).unwrap_err();
        assert!(matches!(e, ConfigError::Input(InputError::TooLarge { .. })));
        assert!(e.to_string().contains("huge.toml"), "{e}");
    }

    #[test]
    fn ratio_and_resolution() {
        assert_eq!(integer_ratio("r", 200.0, 50.0).unwrap(), 4);
        assert!(integer_ratio("r", 200.0, 60.0).is_err());
        assert!(integer_ratio("r", 10.0, 50.0).is_err());
        assert!(integer_ratio("r", 1e300, 1e-300).is_err());
        assert_eq!(
            resolve(Path::new("configs/sim.toml"), Path::new("../assets")),
            Path::new("configs/../assets")
        );
        assert_eq!(
            resolve(Path::new("sim.toml"), Path::new("/a")),
            Path::new("/a")
        );
    }
}
