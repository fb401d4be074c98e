//! `c4g info` and `c4g clips`: what the server serves and stores.

use serde_json::json;

use super::{Context, clip_line, clip_summary, emit, emit_json, emit_line, model_line};

#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// A clip id; without it, the model and every clip.
    clip: Option<String>,
}

pub async fn run(cx: &Context, args: InfoArgs) -> anyhow::Result<()> {
    if let Some(id) = args.clip {
        let clip = cx.client.clip(&id).await?;
        return if cx.json {
            emit_json(&clip)
        } else {
            emit(&clip_summary(&clip))
        };
    }
    let models = cx.client.models().await?;
    let clips = cx.client.clips().await?;
    if cx.json {
        return emit_json(&json!({
            "server": cx.client.base_url().as_str(),
            "models": models,
            "clips": clips,
        }));
    }
    let mut text = format!("server  {}\n", cx.client.base_url());
    for model in &models {
        text.push_str(&format!("model   {}\n", model_line(model)));
    }
    text.push_str(&format!("clips   {}\n", clips.len()));
    for clip in &clips {
        text.push_str(&format!("  {}\n", clip_line(clip)));
    }
    emit(&text)
}

pub async fn clips(cx: &Context) -> anyhow::Result<()> {
    let clips = cx.client.clips().await?;
    if cx.json {
        return emit_json(&json!({ "clips": clips }));
    }
    if clips.is_empty() {
        return emit_line("no clips");
    }
    let text: String = clips.iter().map(|c| clip_line(c) + "\n").collect();
    emit(&text)
}
