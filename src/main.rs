//! The `pipeline` command-line tool.
fn main() -> anyhow::Result<()> {
    Ok(())
}
