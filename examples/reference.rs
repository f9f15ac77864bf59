//! Writes the generated reference: `cargo run --example reference -- docs/reference`
//! (what `scripts/reference` runs).

fn main() -> anyhow::Result<()> {
    let dir = std::env::args().nth(1).unwrap_or_else(|| "docs/reference".into());
    pdi_compile::reference::write(std::path::Path::new(&dir))?;
    println!("wrote {dir}");
    Ok(())
}
