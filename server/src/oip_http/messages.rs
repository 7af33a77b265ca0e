//! ModelConfig and ModelStatistics in Triton's HTTP JSON: the protobuf messages' field names,
//! enums by name, numbers as numbers (what `tritonclient.http` reads).

use relreward_proto::inference as pb;
use serde_json::{Map, Value, json};

pub(super) fn config_json(c: pb::ModelConfig) -> Value {
    let data_type =
        |t: i32| pb::DataType::try_from(t).map_or_else(|_| "TYPE_INVALID".to_owned(), |t| t.as_str_name().to_owned());
    let reshape = |r: &Option<pb::ModelTensorReshape>| r.as_ref().map(|r| json!({ "shape": r.shape }));
    let inputs: Vec<Value> = c
        .input
        .iter()
        .map(|i| {
            let mut v =
                json!({ "name": i.name, "data_type": data_type(i.data_type), "dims": i.dims, "optional": i.optional });
            if let Some(r) = reshape(&i.reshape) {
                v["reshape"] = r;
            }
            v
        })
        .collect();
    let outputs: Vec<Value> = c
        .output
        .iter()
        .map(|o| {
            let mut v = json!({ "name": o.name, "data_type": data_type(o.data_type), "dims": o.dims });
            if let Some(r) = reshape(&o.reshape) {
                v["reshape"] = r;
            }
            v
        })
        .collect();
    let parameters: Map<String, Value> =
        c.parameters.iter().map(|(k, p)| (k.clone(), json!({ "string_value": p.string_value }))).collect();
    let mut config = json!({
        "name": c.name,
        "platform": c.platform,
        "backend": c.backend,
        "max_batch_size": c.max_batch_size,
        "input": inputs,
        "output": outputs,
        "parameters": parameters,
    });
    if let Some(pb::model_version_policy::PolicyChoice::Specific(s)) =
        c.version_policy.as_ref().and_then(|p| p.policy_choice.as_ref())
    {
        config["version_policy"] = json!({ "specific": { "versions": s.versions } });
    }
    if let Some(pb::model_config::SchedulingChoice::DynamicBatching(d)) = &c.scheduling_choice {
        let mut batching = json!({
            "preferred_batch_size": d.preferred_batch_size,
            "max_queue_delay_microseconds": d.max_queue_delay_microseconds,
            "preserve_ordering": d.preserve_ordering,
        });
        if let Some(q) = &d.default_queue_policy {
            let action =
                pb::model_queue_policy::TimeoutAction::try_from(q.timeout_action).map_or("REJECT", |a| a.as_str_name());
            batching["default_queue_policy"] = json!({
                "timeout_action": action,
                "default_timeout_microseconds": q.default_timeout_microseconds,
                "allow_timeout_override": q.allow_timeout_override,
                "max_queue_size": q.max_queue_size,
            });
        }
        config["dynamic_batching"] = batching;
    }
    config
}

pub(super) fn statistics_json(s: &pb::ModelStatistics) -> Value {
    let d = |d: &Option<pb::StatisticDuration>| {
        let d = d.unwrap_or_default();
        json!({ "count": d.count, "ns": d.ns })
    };
    let i = s.inference_stats.unwrap_or_default();
    json!({
        "name": s.name,
        "version": s.version,
        "last_inference": s.last_inference,
        "inference_count": s.inference_count,
        "execution_count": s.execution_count,
        "inference_stats": {
            "success": d(&i.success),
            "fail": d(&i.fail),
            "queue": d(&i.queue),
            "compute_input": d(&i.compute_input),
            "compute_infer": d(&i.compute_infer),
            "compute_output": d(&i.compute_output),
            "cache_hit": d(&i.cache_hit),
            "cache_miss": d(&i.cache_miss),
        },
        "batch_stats": [],
    })
}
