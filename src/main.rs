//! The `cooploc` command line. Thin: parses, validates, and calls the library.
fn main() {
    println!("cooploc {}", env!("CARGO_PKG_VERSION"));
}
