//! `rtvtk serve`: the read-only Arrow Flight SQL query service over one or more datasets.

use anyhow::{Context, Result, bail};
use clap::Args;

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// Datasets (`PATH` or `NAME=PATH`; the first one's tables are also unqualified, as in
    /// `rtvtk sql`).
    #[arg(required = true, num_args = 1..)]
    datasets: Vec<String>,
    /// Where to listen, HOST:PORT (port 0 picks a free one; the address is printed at start).
    /// Use 0.0.0.0:PORT to accept other machines.
    #[arg(long, default_value = "127.0.0.1:50051")]
    addr: String,
    /// Memory each query's operators may hold, e.g. `2GiB` (unlimited by default).
    #[arg(long, value_parser = crate::sql::parse_bytes)]
    memory_limit: Option<usize>,
}

pub fn run(a: &ServeArgs) -> Result<()> {
    if let Some(d) = a.datasets.iter().find(|d| !crate::sql::is_dataset(d)) {
        bail!("{d}: not a dataset directory (expected {})", store::MANIFEST_FILE);
    }
    let sources: Vec<query::TraceSource> = a.datasets.iter().map(|d| query::TraceSource::parse(d)).collect();
    let rt = crate::runtime()?;
    rt.block_on(async {
        let options = query::SessionOptions { memory_limit: a.memory_limit, ..Default::default() };
        let ctx = query::session_with(&sources, &options).await?;
        let listener = query::service::bind(&a.addr)?;
        let addr = query::service::local_addr(&listener)?;
        let names: Vec<&str> = sources.iter().map(|s| s.name.as_str()).collect();
        // One line on stdout, flushed, so scripts and tests can read the address.
        println!("rtvtk serve: Arrow Flight SQL on grpc://{addr} (read-only; datasets: {})", names.join(", "));
        use std::io::Write as _;
        std::io::stdout().flush().context("writing the address")?;
        query::service::serve(&ctx, listener, std::future::pending()).await?;
        Ok(())
    })
}
