//! Any request line to the JSON-RPC handler, with a control target that answers every method:
//! never a panic, and every answer is one JSON-RPC 2.0 response (or a batch of them).
#![no_main]

use std::path::PathBuf;

use libfuzzer_sys::fuzz_target;
use relight_daemon::control::rpc::handle_line;
use relight_daemon::control::{
    ControlError, ControlTarget, EngineInfo, OutputRequest, StatusReport,
};
use serde_json::{Map, Value, json};

struct Target;

impl ControlTarget for Target {
    fn status(&self) -> StatusReport {
        StatusReport::default()
    }
    fn engine_list(&self) -> Vec<EngineInfo> {
        Vec::new()
    }
    fn engine_set(&self, name: &str) -> Result<(), ControlError> {
        if name == "passthrough" {
            Ok(())
        } else {
            Err(ControlError::engine_unknown(name))
        }
    }
    fn engine_params_get(&self) -> Value {
        json!({})
    }
    fn engine_params_set(&self, params: Map<String, Value>) -> Result<Value, ControlError> {
        Ok(Value::Object(params))
    }
    fn record_start(&self, request: OutputRequest) -> Result<PathBuf, ControlError> {
        Ok(request.path.unwrap_or_default())
    }
    fn record_stop(&self) -> Result<Value, ControlError> {
        Err(ControlError::failed("not recording"))
    }
    fn snapshot(&self, request: OutputRequest) -> Result<Vec<PathBuf>, ControlError> {
        Ok(request.path.into_iter().collect())
    }
    fn config_reload(&self) -> Result<Value, ControlError> {
        Ok(json!({}))
    }
}

fn is_response(value: &Value) -> bool {
    value["jsonrpc"] == "2.0"
        && value.get("id").is_some()
        && (value.get("result").is_some() != value.get("error").is_some())
}

fuzz_target!(|data: &[u8]| {
    if let Some(response) = handle_line(data, &Target) {
        let value: Value = serde_json::from_str(&response).expect("a response is JSON");
        match &value {
            Value::Array(batch) => assert!(batch.iter().all(is_response), "{response}"),
            single => assert!(is_response(single), "{response}"),
        }
    }
});
