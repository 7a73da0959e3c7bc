//! Generates the Rust bindings of the cooploc MAVLink dialect (`dialects/cooploc.xml`, which
//! includes the vendored ardupilotmega.xml and, through it, common.xml) into OUT_DIR with mavlink-bindgen, extensions on.

fn main() {
    // Read at run time: a build script binary reused from another checkout of this package
    // (a shared CARGO_TARGET_DIR) must not read that checkout's dialect.
    let manifest_dir = std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
    let dialects = std::path::Path::new(&manifest_dir).join("../../dialects");
    for xml in [
        "cooploc.xml",
        "ardupilotmega.xml",
        "common.xml",
        "uAvionix.xml",
        "icarous.xml",
        "loweheiser.xml",
        "cubepilot.xml",
        "csAirLink.xml",
        "standard.xml",
        "minimal.xml",
    ] {
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
