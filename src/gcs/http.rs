//! The ground station's web server: `GET /` is one self-contained page (no CDN, no network: plain
//! JavaScript and canvas, `page.html` next to this file), `GET /api/state` the JSON it polls
//! ([`super::state::StateJson`]).

use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::routing::get;

use super::runner::Clock;
use super::state::GcsState;

/// The page, built into the binary.
pub const PAGE_HTML: &str = include_str!("page.html");

/// Points per series in `/api/state` (tracks, error curves).
pub const MAX_POINTS: usize = 1500;

#[derive(Clone)]
struct AppState {
    state: Arc<Mutex<GcsState>>,
    clock: Clock,
}

async fn page() -> impl IntoResponse {
    ([(header::CACHE_CONTROL, "no-store")], Html(PAGE_HTML))
}

async fn api_state(State(app): State<AppState>) -> impl IntoResponse {
    let now = app.clock.now();
    // A poisoned lock means a panic elsewhere; the data is still worth showing.
    let snapshot = app.state.lock().unwrap_or_else(|e| e.into_inner()).snapshot(now, MAX_POINTS);
    ([(header::CACHE_CONTROL, "no-store")], axum::Json(snapshot))
}

/// The routes, over the shared state.
pub fn router(state: Arc<Mutex<GcsState>>, clock: Clock) -> Router {
    Router::new().route("/", get(page)).route("/api/state", get(api_state)).with_state(AppState { state, clock })
}
