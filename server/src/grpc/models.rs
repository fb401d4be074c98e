//! `ListModels`: the loaded model (REST: `api/models.rs`).

use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status};

use super::context::Grpc;

pub(super) async fn list_models(
    grpc: &Grpc,
    _: Request<pb::ListModelsRequest>,
) -> Result<Response<pb::ListModelsResponse>, Status> {
    let service = grpc.service()?;
    let m = service.engine.manifest();
    Ok(Response::new(pb::ListModelsResponse {
        models: vec![pb::Model {
            name: m.name.clone(),
            version: m.version.clone(),
            input_width: m.input.width,
            input_height: m.input.height,
            gaussians_per_set: m.gaussian_count as u32,
            manifest_json: crate::api::models::describe(service).to_string(),
        }],
    }))
}
