//! `rtvtk demo`: record the Cornell box, summarize the trace, draw one pixel's tree over the image.

use std::path::PathBuf;

use anyhow::Result;
use rl::Dataset;

/// `rtvtk demo`: render and record the Cornell box, then print a summary of the trace.
#[derive(clap::Args)]
pub struct DemoArgs {
    /// Dataset directory to write (default: a fresh temporary directory).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Image size, WxH.
    #[arg(long, default_value = "128x128", value_parser = crate::args::parse_size)]
    pub size: (u32, u32),
    /// Samples per pixel.
    #[arg(long, default_value_t = 8)]
    pub spp: u32,
    /// Tracing threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

impl DemoArgs {
    pub fn run(&self) -> Result<()> {
        run(self.out.clone(), self.size, self.spp, self.threads)
    }
}

/// Renders and records the Cornell box with the path tracer, then summarizes the trace.
pub fn run(out: Option<PathBuf>, (w, h): (u32, u32), spp: u32, threads: usize) -> Result<()> {
    let dir = out.unwrap_or_else(|| std::env::temp_dir().join(format!("rtvtk-demo-{}", std::process::id())));
    // The `record` command with its own defaults, so the demo cannot drift from it.
    let (size, spp, threads) = (format!("{w}x{h}"), spp.to_string(), threads.max(1).to_string());
    let dir_arg = dir.to_string_lossy().to_string();
    let args = <crate::record::RecordArgs as clap::Parser>::try_parse_from([
        "record",
        "--scene",
        "cornell",
        "--out",
        &dir_arg,
        "--size",
        &size,
        "--spp",
        &spp,
        "--threads",
        &threads,
    ])?;
    crate::record::run(&args)?;
    println!();
    crate::info::run(&dir, false)?;
    println!();
    let ds = Dataset::open(&dir)?;
    let (x, y) = (w / 2, h * 3 / 4);
    if let Some(t) = ds.trees_at_pixel(x, y, Some(0))?.first() {
        println!("the ray tree of pixel ({x}, {y}), sample 0:");
        crate::tree::print_tree(&ds, t);
    }
    println!();
    // The layered picture: the path-traced image, the scene's depth, and that tree's rays.
    let picture = dir.join("demo.png");
    let render = <crate::render::RenderArgs as clap::Parser>::try_parse_from([
        "render".to_string(),
        dir_arg.clone(),
        "--layers".into(),
        "image,composition,rays".into(),
        "--pixel".into(),
        format!("{x},{y}"),
        "--sample".into(),
        "0".into(),
        "--line-width".into(),
        "2".into(),
        "--out".into(),
        picture.to_string_lossy().to_string(),
    ])?;
    let drawn = crate::render::render_to_png(&render);
    match &drawn {
        Ok(_) => println!(
            "picture: {} (that tree's rays over the path-traced image, hidden behind geometry)",
            picture.display()
        ),
        Err(e) => eprintln!("no picture: {e:#}"),
    }
    println!();
    if cfg!(feature = "sql") {
        println!("try: rtvtk view {}             # the interactive viewer", dir.display());
    } else {
        // The demo's quick first build leaves out the SQL engine, and the viewer with it.
        println!("try: cargo run -- view {}      # the interactive viewer (a default build)", dir.display());
    }
    println!("     rtvtk tree {} --pixel {},{}", dir.display(), w / 2, h / 2);
    println!(
        "     rtvtk render {} --layers image,composition,rays --pixel {},{} --out layers.png",
        dir.display(),
        w / 2,
        h / 2
    );
    println!("     rtvtk check {}", dir.display());
    // The trace is written either way; a missing picture still fails the command (exit 1).
    drawn
        .map(|_| ())
        .map_err(|e| anyhow::anyhow!("the trace is written ({}), but demo.png is not: {e:#}", dir.display()))
}
