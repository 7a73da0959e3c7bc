//! The node's files kept across restarts, each read at start and written whole or not at all (a
//! temporary file beside it, renamed over it): the signing timestamp (`--signing-state`,
//! [`crate::protocol::signing`]) and the navigation state (`--state-file`, [`super::saved`]).

use super::error::NodeError;

/// Reads a signing state file: 0 when it does not exist yet.
pub fn load_signing_state(path: &std::path::Path) -> Result<u64, NodeError> {
    match std::fs::read_to_string(path) {
        Ok(text) => crate::protocol::signing::parse_state(&text)
            .map_err(|e| NodeError::Invalid(format!("signing state {}: {e}", path.display()))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
        Err(e) => Err(NodeError::io(format!("signing state {}", path.display()))(e)),
    }
}

/// Writes a file whole or not at all (a temporary file beside it, renamed over it): the signing
/// state, the navigation state.
pub fn save_whole(path: &std::path::Path, text: &str) -> std::io::Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, path)
}

/// Reads a navigation state file: None when it does not exist yet, or when it cannot be used
/// (said on stdout and in the trace, with the reason: a node with a damaged state file still
/// starts, as it would without one).
pub fn load_nav_state(path: &std::path::Path, id: crate::estimation::PlatformId) -> Option<super::saved::SavedState> {
    let said = |why: String| {
        println!("node {id} state file {} not used: {why}", path.display());
        tracing::warn!(path = %path.display(), why, "state file not used");
        None
    };
    match std::fs::read_to_string(path) {
        Ok(text) => super::saved::SavedState::parse(&text).or_else(|why| said(why).ok_or(())).ok(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => said(e.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A missing state file is a first start; a damaged one is not used (the node starts as
    /// without it); a good one reads back; a save leaves no temporary file behind.
    #[test]
    fn state_files_are_read_whole_or_not_used() {
        let dir = std::env::temp_dir().join(format!("cooploc-runner-state-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("node.state");
        assert_eq!(load_nav_state(&path, 3), None);
        std::fs::write(&path, "{\"format\":1,").unwrap();
        assert_eq!(load_nav_state(&path, 3), None);
        let origin = crate::geodesy::GeoOrigin { lat_deg: 34.7, lon_deg: 0.0, alt_m: 0.0 };
        let model = crate::estimation::nav::NavModel::Planar {
            config: crate::estimation::planar::PlanarConfig::from_sample_sigmas(0.05, 0.01, 20.0),
            initial_sigma: crate::estimation::planar::PlanarSigma { pos_m: 0.5, yaw_rad: 0.02 },
        };
        let state = crate::estimation::planar::PlanarState { pos_ned_m: nalgebra::Vector3::new(3.0, 4.0, 0.0), yaw_rad: 0.1 };
        let filter = crate::estimation::nav::NavFilter::new(model, crate::time::TimeUs(7_000_000), state.into()).unwrap();
        let saved = super::super::saved::SavedState::of(3, &origin, &filter);
        save_whole(&path, &saved.to_text()).unwrap();
        assert_eq!(load_nav_state(&path, 3), Some(saved));
        assert!(!dir.join("node.state.tmp").exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
