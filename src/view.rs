//! `rtvtk view`: the interactive viewer.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use rtvtk_viewer::{Source, ViewerOptions};

#[derive(Args)]
pub struct ViewArgs {
    /// Dataset directories (the first is opened; the others are in the source menu and in the
    /// SQL console under their names).
    pub datasets: Vec<PathBuf>,
    /// A scene to trace with no dataset (built-in name such as `cornell`, or an OBJ file).
    #[arg(long)]
    pub scene: Option<String>,
    /// Draw a dataset an `rtvtk serve` service serves (`grpc://HOST:PORT`): every layer, the
    /// console, plots and inspector ask the service (no dataset directory is read here).
    #[arg(long, conflicts_with_all = ["datasets", "scene"])]
    pub connect: Option<String>,
    /// The service's dataset to draw, where it serves several (default: its first).
    #[arg(long, requires = "connect")]
    pub dataset: Option<String>,
    /// A file holding the service's bearer token.
    #[arg(long, requires = "connect")]
    pub token_file: Option<PathBuf>,
    /// Forget the saved layout (component settings and history are kept).
    #[arg(long)]
    pub reset_layout: bool,
    /// Write a screenshot of the window once everything is drawn, then close.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// The tracer of the live image and of Ctrl-click (immediate mode) in the default layers:
    /// cpu or gpu (per layer: the image layer's `source`, the ray layer's `tracer`).
    #[arg(long, default_value = "path", value_parser = crate::args::parse_tracer)]
    pub tracer: renderers::TracerChoice,
}

pub fn run(args: &ViewArgs) -> Result<()> {
    let mut sources = Vec::new();
    for d in &args.datasets {
        if !d.is_dir() {
            bail!("{} is not a dataset directory", d.display());
        }
        sources.push(Source::Dataset(d.clone()));
    }
    if let Some(s) = &args.scene {
        sources.push(Source::Scene(s.clone()));
    }
    if args.connect.is_some() {
        sources.push(Source::Served(args.dataset.clone().unwrap_or_default()));
    }
    if sources.is_empty() {
        sources.push(Source::Scene("cornell".into()));
    }
    let token = match &args.token_file {
        Some(p) => Some(
            std::fs::read_to_string(p)
                .with_context(|| format!("cannot read the token file {}", p.display()))?
                .trim()
                .to_string(),
        ),
        None => None,
    };
    let options = ViewerOptions {
        sources,
        connect: args.connect.clone(),
        token,
        reset_layout: args.reset_layout,
        screenshot: args.screenshot.clone(),
        tracer: args.tracer,
        engine: None,
    };
    rtvtk_viewer::run(options).context("the viewer failed")
}
