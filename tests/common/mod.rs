#![allow(dead_code)] // each test binary uses some of the helpers

//! Helpers shared by the integration tests.

/// The Python of the test virtualenv (`COOPLOC_PYTHON`, set by tests/run-all.sh). Under
/// `CI=true` a missing one fails the test; elsewhere the test says it skipped, naming `what`.
pub fn python(what: &str) -> Option<String> {
    match std::env::var("COOPLOC_PYTHON") {
        Ok(p) => Some(p),
        Err(_) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("COOPLOC_PYTHON is not set: run the tests through tests/run-all.sh")
        }
        Err(_) => {
            eprintln!("SKIPPED: {what} needs COOPLOC_PYTHON (tests/run-all.sh sets it)");
            None
        }
    }
}

/// Headless Chromium (`COOPLOC_CHROMIUM`, or `chromium` / `chromium-browser` on the PATH;
/// tests/run-all.sh installs Debian's package when it is missing). Under `CI=true` a missing
/// one fails the test; elsewhere the test says it skipped, naming `what`.
#[allow(dead_code)]
pub fn chromium(what: &str) -> Option<std::path::PathBuf> {
    let candidates = std::env::var_os("COOPLOC_CHROMIUM").map(std::path::PathBuf::from).into_iter().chain(
        std::env::var_os("PATH").into_iter().flat_map(|paths| {
            std::env::split_paths(&paths)
                .flat_map(|dir| ["chromium", "chromium-browser"].map(|name| dir.join(name)))
                .collect::<Vec<_>>()
        }),
    );
    for c in candidates {
        if c.is_file() {
            return Some(c);
        }
    }
    if std::env::var("CI").as_deref() == Ok("true") {
        panic!("{what} needs Chromium and none was found: tests/run-all.sh installs it (apt-get install chromium)");
    }
    eprintln!("SKIPPED: {what} needs Chromium (`apt-get install chromium`, or run tests/run-all.sh)");
    None
}
