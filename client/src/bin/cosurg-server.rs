//! `cosurg-server`: the coordinator. All logic lives in the `cosurg-server` package
//! (crate `server` in this workspace), module `cli`.
fn main() -> anyhow::Result<()> {
    server::cli::main()
}
