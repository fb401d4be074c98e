//! `c4g delete`: remove a clip and its cached features.

use serde_json::json;

use super::{Context, emit_json, emit_line};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The clip id.
    clip: String,
}

pub async fn run(cx: &Context, args: Args) -> anyhow::Result<()> {
    cx.client.delete(&args.clip).await?;
    if cx.json {
        emit_json(&json!({ "deleted": args.clip }))
    } else {
        emit_line(format!("deleted {}", args.clip))
    }
}
