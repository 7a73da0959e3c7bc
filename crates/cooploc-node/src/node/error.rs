//! What can stop a node: its links not opening, its settings, its vehicle going away. Typed, so
//! that a caller (the binary, the demo, a test) sees which; each message names the step that
//! failed and, for I/O, the operating system's reason.

/// A node's failure.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// An I/O step (binding, resolving, joining a group, opening a device) failed.
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    /// A setting that cannot work (an address that is not one, a platform id out of range).
    #[error("{0}")]
    Invalid(String),
    /// The node's configuration was refused by its core.
    #[error("node configuration: {0}")]
    Config(#[from] super::core::NodeConfigError),
    /// The vehicle's link closed under the node.
    #[error("vehicle link closed")]
    VehicleClosed,
}

impl NodeError {
    /// An I/O failure of the step `what`, for `map_err`.
    pub fn io(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> NodeError {
        let what = what.into();
        move |source| NodeError::Io { what, source }
    }
}
