//! The code's shape, measured on its sources (issue 34): no function of the library or the
//! binary over 150 lines, and the node's tokio runner under 300 lines in all (everything else a node does is in the sans-io
//! node shell, `crates/cooploc-node/src/node/shell.rs`).

use std::path::{Path, PathBuf};
use syn::visit::Visit;

/// The longest a function may be, lines from `fn` to its closing brace.
const MAX_FN_LINES: usize = 150;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// Every function with a body: (name, first line, lines).
/// The library's and the binary's sources: `src/` and every crate's `crates/*/src/`.
fn library_sources(root: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    rust_files(&root.join("src"), &mut files);
    for krate in std::fs::read_dir(root.join("crates")).unwrap() {
        rust_files(&krate.unwrap().path().join("src"), &mut files);
    }
    files.sort();
    files
}

/// A source's path from the repository's root, with `/`.
fn relative(root: &Path, file: &Path) -> String {
    file.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/")
}

/// The path of a source inside its crate's `src/` (`crates/cooploc-node/src/node/shell.rs`:
/// `node/shell.rs`).
fn in_crate(rel: &str) -> &str {
    rel.strip_prefix("src/").unwrap_or_else(|| rel.split_once("/src/").map_or(rel, |(_, r)| r))
}

#[derive(Default)]
struct Functions(Vec<(String, usize, usize)>);

impl Functions {
    fn add(&mut self, name: &syn::Ident, start: proc_macro2::Span, block: &syn::Block) {
        let (first, last) = (start.start().line, block.brace_token.span.close().end().line);
        self.0.push((name.to_string(), first, last + 1 - first));
    }
}

impl<'ast> Visit<'ast> for Functions {
    fn visit_item_fn(&mut self, f: &'ast syn::ItemFn) {
        self.add(&f.sig.ident, f.sig.fn_token.span, &f.block);
        syn::visit::visit_item_fn(self, f);
    }
    fn visit_impl_item_fn(&mut self, f: &'ast syn::ImplItemFn) {
        self.add(&f.sig.ident, f.sig.fn_token.span, &f.block);
        syn::visit::visit_impl_item_fn(self, f);
    }
    fn visit_trait_item_fn(&mut self, f: &'ast syn::TraitItemFn) {
        if let Some(block) = &f.default {
            self.add(&f.sig.ident, f.sig.fn_token.span, block);
        }
        syn::visit::visit_trait_item_fn(self, f);
    }
}

fn functions(source: &str) -> Vec<(String, usize, usize)> {
    let file = syn::parse_file(source).expect("the source parses");
    let mut found = Functions::default();
    found.visit_file(&file);
    found.0
}

#[test]
fn no_function_of_the_library_or_the_binary_is_over_150_lines() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let files = library_sources(root);
    assert!(files.len() > 50, "the sources: {}", files.len());
    assert!(files.iter().any(|f| f.ends_with("crates/cooploc-node/src/node/core.rs")), "the crates' sources are measured too");
    assert!(files.iter().any(|f| f.ends_with("src/bin/cooploc/node.rs")), "the binary's sources are measured too");
    let mut long = Vec::new();
    let mut count = 0;
    for file in &files {
        let source = std::fs::read_to_string(file).unwrap();
        for (name, line, lines) in functions(&source) {
            count += 1;
            if lines > MAX_FN_LINES {
                long.push(format!("{}:{line} {name}: {lines} lines", relative(root, file)));
            }
        }
    }
    assert!(count > 1000, "functions found: {count}");
    assert!(long.is_empty(), "functions over {MAX_FN_LINES} lines:\n{}", long.join("\n"));
}

#[test]
fn the_node_runner_is_under_300_lines_and_its_run_under_100() {
    let runner = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/node/runner.rs")).unwrap();
    let lines = runner.lines().count();
    assert!(lines < 300, "src/node/runner.rs has {lines} lines");
    // its run: the sockets and a select! over them, the shell doing the rest
    let run = functions(&runner).into_iter().find(|(name, _, _)| name == "run").expect("node::runner::run");
    assert!(run.2 < 100, "node::runner::run has {} lines", run.2);
}

/// The measure itself: from `fn` to the closing brace, nested functions counted on their own,
/// braces in strings and comments not mistaken for blocks.
#[test]
fn functions_are_measured_from_fn_to_their_closing_brace() {
    let source = "/// doc\n#[inline]\npub fn a() {\n    let s = \"}}}\";\n    // }\n    fn inner() {}\n}\n\nimpl X {\n    fn b(&self)\n    {\n    }\n}\n";
    assert_eq!(functions(source), [("a".to_string(), 3, 5), ("inner".to_string(), 6, 1), ("b".to_string(), 10, 3)]);
}

/// What each top-level module of the library may import (`crate::X`), bottom up, as the layer
/// table of docs/architecture.md says: the math at the bottom, the wire layer above it, the
/// sans-io cores above that, the adapters (sockets, files, tokio) on top. The simulated world
/// (`sitl`) sits beside the math; the node does not import it.
const MAY_IMPORT: &[(&str, &[&str])] = &[
    ("time", &[]),
    ("geodesy", &[]),
    ("estimation", &["time", "geodesy"]),
    ("sitl", &["estimation", "time", "geodesy"]),
    ("protocol", &["estimation", "time", "geodesy"]),
    ("view", &["estimation", "protocol", "time", "geodesy"]),
    ("node", &["estimation", "protocol", "time", "geodesy"]),
    ("dataset", &["estimation", "protocol", "time", "geodesy"]),
    ("gcs", &["estimation", "protocol", "view", "time", "geodesy"]),
    ("simulator", &["estimation", "protocol", "node", "sitl", "time", "geodesy"]),
    ("experiment", &["estimation", "protocol", "node", "sitl", "simulator", "time", "geodesy"]),
    ("recording", &["estimation", "protocol", "view", "node", "dataset", "gcs", "time", "geodesy"]),
    ("replay", &["estimation", "protocol", "node", "recording", "sitl", "experiment", "time", "geodesy"]),
    (
        "demo",
        &[
            "estimation",
            "protocol",
            "node",
            "gcs",
            "view",
            "recording",
            "replay",
            "sitl",
            "simulator",
            "experiment",
            "time",
            "geodesy",
        ],
    ),
];

/// Files of a core's module that are adapters (sockets, files, tokio): they may also import the
/// recording and the view.
const ADAPTER_FILES: &[&str] = &[
    "src/node/runner.rs",
    "src/node/range_link.rs",
    "src/node/coop_link.rs",
    "src/node/vehicle_link.rs",
    "src/gcs/runner.rs",
    "src/gcs/http.rs",
    "src/gcs/foxglove_live.rs",
    "src/gcs/log.rs",
    "src/dataset/log.rs",
    "src/simulator/runner.rs",
];

/// Wrong-way imports still to be removed (issue 34), each `file -> module`. The test fails on any
/// import outside the table and on a listed one that no longer occurs, so the list only shrinks.
const NOT_YET: &[(&str, &str)] = &[];

/// The `crate::X` modules a source file's code names (comments and test modules left out).
fn crate_imports(source: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (i, line) in source.lines().enumerate() {
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        let code = line.split("//").next().unwrap_or("");
        let mut rest = code;
        while let Some(at) = rest.find("crate::") {
            let name: String = rest[at + 7..].chars().take_while(|c| c.is_ascii_lowercase() || *c == '_').collect();
            out.push((i + 1, name));
            rest = &rest[at + 7..];
        }
    }
    out
}

#[test]
fn every_module_imports_only_the_layers_below_it() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let files = library_sources(root);
    let mut wrong = Vec::new();
    let mut seen_not_yet = Vec::new();
    for file in &files {
        let rel = relative(root, file);
        let inner = in_crate(&rel);
        if inner.starts_with("bin/") || inner == "lib.rs" || rel.ends_with("/tests.rs") {
            continue;
        }
        let module = inner.split('/').next().unwrap().trim_end_matches(".rs").to_string();
        let allowed = MAY_IMPORT
            .iter()
            .find(|(m, _)| *m == module)
            .unwrap_or_else(|| panic!("{rel}: module {module} has no place in the table"))
            .1;
        let adapter = ADAPTER_FILES.contains(&rel.as_str());
        for (line, name) in crate_imports(&std::fs::read_to_string(file).unwrap()) {
            if name == module || allowed.contains(&name.as_str()) || (adapter && (name == "recording" || name == "view")) {
                continue;
            }
            if NOT_YET.contains(&(rel.as_str(), name.as_str())) {
                seen_not_yet.push((rel.clone(), name));
                continue;
            }
            wrong.push(format!("{rel}:{line}: {module} imports {name}"));
        }
    }
    assert!(wrong.is_empty(), "imports against the layers:\n{}", wrong.join("\n"));
    for (file, name) in NOT_YET {
        assert!(seen_not_yet.iter().any(|(f, n)| f == file && n == name), "{file} no longer imports {name}: take it off NOT_YET");
    }
}

#[test]
fn crate_paths_are_found_in_code_and_not_in_comments() {
    let source = "use crate::estimation::Method; // crate::gcs\n/// [`crate::view`]\nlet x = crate::time::TimeUs(1) + crate::geodesy::f();\n#[cfg(test)]\nuse crate::sitl;\n";
    let names: Vec<String> = crate_imports(source).into_iter().map(|(_, n)| n).collect();
    assert_eq!(names, ["estimation", "time", "geodesy"]);
}

/// The workspace's crates as the Crates table of docs/architecture.md lists them: (crate, its
/// modules, the crates of the workspace it depends on).
fn crates_table() -> Vec<(String, Vec<String>, Vec<String>)> {
    let doc = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/architecture.md")).unwrap();
    let start = doc.find("| crate | folder | modules | depends on |").expect("docs/architecture.md has the Crates table");
    let names = |cell: &str| -> Vec<String> {
        let mut v: Vec<String> = cell.split('`').skip(1).step_by(2).map(str::to_string).collect();
        v.sort();
        v
    };
    doc[start..]
        .lines()
        .skip(2)
        .take_while(|l| l.starts_with('|'))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            (cells[1].trim_matches('`').to_string(), names(cells[3]), names(cells[4]))
        })
        .collect()
}

/// Each workspace crate's normal dependencies among the workspace's crates, from `cargo metadata`.
fn crate_graph() -> Vec<(String, Vec<String>)> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--no-deps", "--offline"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo metadata runs");
    assert!(out.status.success(), "cargo metadata: {}", String::from_utf8_lossy(&out.stderr));
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let members: Vec<String> =
        meta["packages"].as_array().unwrap().iter().map(|p| p["name"].as_str().unwrap().to_string()).collect();
    let mut graph: Vec<(String, Vec<String>)> = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let mut deps: Vec<String> = p["dependencies"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|d| d["kind"].is_null() && members.contains(&d["name"].as_str().unwrap().to_string()))
                .map(|d| d["name"].as_str().unwrap().to_string())
                .collect();
            deps.sort();
            (p["name"].as_str().unwrap().to_string(), deps)
        })
        .collect();
    graph.sort();
    graph
}

/// The dependency graph of the workspace is the architecture's Crates table (issue 34): a crate
/// that imports a layer above it does not compile, and one that depends on a crate the table
/// does not give it fails here. The node does not depend on the simulated world.
#[test]
fn the_crate_graph_is_the_architecture_table() {
    let mut table: Vec<(String, Vec<String>)> = crates_table().into_iter().map(|(c, _, d)| (c, d)).collect();
    table.sort();
    let graph = crate_graph();
    assert!(graph.len() >= 6, "the workspace's crates: {graph:?}");
    assert_eq!(graph, table, "cargo metadata (left) against docs/architecture.md's Crates table (right)");
    let node = graph.iter().find(|(c, _)| c == "cooploc-node").expect("a node crate");
    assert!(!node.1.iter().any(|d| d == "cooploc-sitl"), "the node depends on the simulated world: {:?}", node.1);
}

/// Each crate's own top-level modules (the `pub mod` lines of its lib.rs; the layers below it are
/// re-exported, not its own) are the ones the table lists.
#[test]
fn every_crate_holds_the_modules_the_table_gives_it() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (krate, modules, _) in crates_table() {
        let lib = match krate.as_str() {
            "cooploc" => root.join("src/lib.rs"),
            "cooploc-py" => continue,
            other => root.join("crates").join(other).join("src/lib.rs"),
        };
        let source = std::fs::read_to_string(&lib).unwrap_or_else(|e| panic!("{}: {e}", lib.display()));
        let mut own: Vec<String> =
            source.lines().filter_map(|l| l.strip_prefix("pub mod ")).map(|m| m.trim_end_matches(';').to_string()).collect();
        own.sort();
        assert_eq!(own, modules, "{krate}: the modules of {} against the table", lib.display());
    }
}
