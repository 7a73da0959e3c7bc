//! Generates the Rust bindings of the cooploc MAVLink dialect (`dialects/cooploc.xml`, which
//! includes the vendored common.xml) into OUT_DIR with mavlink-bindgen, extensions on.

fn main() {
    let dialects = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("dialects");
    for xml in ["cooploc.xml", "common.xml", "standard.xml", "minimal.xml"] {
        println!("cargo:rerun-if-changed={}", dialects.join(xml).display());
    }
    let out_dir = std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR");
    if let Err(e) =
        mavlink_bindgen::generate(mavlink_bindgen::XmlDefinitions::Files(vec![dialects.join("cooploc.xml")]), &out_dir)
    {
        eprintln!("generating the cooploc MAVLink dialect from {}: {e}", dialects.display());
        std::process::exit(1);
    }
}
