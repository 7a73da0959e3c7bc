//! The code's shape, measured on its sources (issue 34): no function of the library or the
//! binary over 150 lines, and the node's tokio runner under 300 lines in all (everything else a node does is in the sans-io
//! node shell, `src/node/shell.rs`).

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
    let mut files = Vec::new();
    rust_files(&root.join("src"), &mut files);
    files.sort();
    assert!(files.len() > 50, "the sources: {}", files.len());
    assert!(files.iter().any(|f| f.ends_with("src/bin/cooploc/node.rs")), "the binary's sources are measured too");
    let mut long = Vec::new();
    let mut count = 0;
    for file in &files {
        let source = std::fs::read_to_string(file).unwrap();
        for (name, line, lines) in functions(&source) {
            count += 1;
            if lines > MAX_FN_LINES {
                long.push(format!("{}:{line} {name}: {lines} lines", file.strip_prefix(root).unwrap().display()));
            }
        }
    }
    assert!(count > 1000, "functions found: {count}");
    assert!(long.is_empty(), "functions over {MAX_FN_LINES} lines:\n{}", long.join("\n"));
}

#[test]
fn the_node_runner_is_under_300_lines() {
    let runner = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/node/runner.rs")).unwrap();
    let lines = runner.lines().count();
    assert!(lines < 300, "src/node/runner.rs has {lines} lines");
}

/// The measure itself: from `fn` to the closing brace, nested functions counted on their own,
/// braces in strings and comments not mistaken for blocks.
#[test]
fn functions_are_measured_from_fn_to_their_closing_brace() {
    let source = "/// doc\n#[inline]\npub fn a() {\n    let s = \"}}}\";\n    // }\n    fn inner() {}\n}\n\nimpl X {\n    fn b(&self)\n    {\n    }\n}\n";
    assert_eq!(functions(source), [("a".to_string(), 3, 5), ("inner".to_string(), 6, 1), ("b".to_string(), 10, 3)]);
}
