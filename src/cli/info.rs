//! `nerflabel info`: validate a scan and print its summary.

use super::InfoArgs;
use anyhow::Context;

pub fn run(args: &InfoArgs) -> anyhow::Result<()> {
    let scan = nerflabel::scan::load(&args.scan.scan, &args.scan.load_options())
        .with_context(|| format!("cannot read the scan {}", args.scan.scan.display()))?;
    let summary = nerflabel::scan::summarize(&scan);
    println!("{summary:?}");
    Ok(())
}
