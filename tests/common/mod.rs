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
