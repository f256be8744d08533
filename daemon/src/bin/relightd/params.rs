//! `--param name=value`, shared by the subcommands that build an engine.

use anyhow::{Context, Result};
use serde_json::{Map, Value};

/// `--param name=value` arguments as engine parameters (values as JSON where they parse).
pub fn parse_params(params: &[String]) -> Result<Map<String, Value>> {
    let mut map = Map::new();
    for param in params {
        let (key, value) = relight_engines::params::parse_assignment(param)
            .with_context(|| format!("--param `{param}`: expected name=value"))?;
        map.insert(key.to_owned(), value);
    }
    Ok(map)
}
