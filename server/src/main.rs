//! `cosurg-server`: the coordinator. All logic lives in this package's library, module `cli`.
fn main() -> anyhow::Result<()> {
    cosurg_server::cli::main()
}
