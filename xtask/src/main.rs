//! `cargo xtask`: experiment recipes, benchmarks and demos.

fn main() {
    eprintln!("usage: cargo xtask <command>");
    std::process::exit(2);
}
