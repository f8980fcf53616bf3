//! Citations that resolve: every relative link of the repository's markdown (README.md,
//! docs/, fuzz/README.md, data/README.md), with its `#anchor` checked against the
//! target's headings by GitHub's slug rule, and every repository path cited in `.rs`
//! comments, in the `bench/` scripts and in the markdown must exist: a backticked path
//! under crates/, docs/, bench/, fuzz/, data/ or .ci/ from the root, or under tests/,
//! src/, examples/, benches/ of a crate, with an optional #anchor; and a bare (not
//! backticked) word that starts with one of the root folders. No code or doc may cite the
//! design notes that are not in the repository. Each failure names the file, the line and
//! the target. Std only, no network: external links (`http://`, `https://`, `mailto:`) are
//! not followed. `.ci/run` runs this test (its `cargo test --workspace --release`).
//!
//! Pitfalls: paths with placeholders (`<experiment>`, `{dir}`, `*`, `$`, `...`, an
//! upper-case segment such as `TARGET`) are skipped; a bare word loses its trailing
//! punctuation (`docs/<page>.md.` cites `docs/<page>.md`);
//! `tests/`, `src/`, `examples/` and `benches/` paths are resolved against the citing
//! file's crate first, then (from markdown) against every crate; text in fenced code
//! blocks is neither a link nor a heading.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};

/// The repository root (this crate is `crates/headalign`).
fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Files under `dir` with extension `ext`, skipping `target` and hidden directories.
fn walk(dir: &Path, ext: &str, out: &mut Vec<PathBuf>) {
    let Ok(entries) = fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if path.is_dir() {
            if name != "target" && !name.starts_with('.') {
                walk(&path, ext, out);
            }
        } else if path.extension().is_some_and(|e| e == ext) {
            out.push(path);
        }
    }
}

/// The markdown files whose links are checked.
fn markdown_files(root: &Path) -> Vec<PathBuf> {
    let mut files = vec![root.join("README.md"), root.join("fuzz/README.md"), root.join("data/README.md")];
    walk(&root.join("docs"), "md", &mut files);
    files.retain(|f| f.is_file());
    files
}

/// Lines of a markdown file outside fenced code blocks, with their 1-based numbers.
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut fenced = false;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        } else if !fenced {
            out.push((i + 1, line));
        }
    }
    out
}

/// GitHub's anchor of a heading: link targets dropped, lower case, every character but
/// letters, digits, `-`, `_` and spaces removed, spaces turned into `-`.
fn slug(heading: &str) -> String {
    let mut text = String::new();
    let mut rest = heading;
    // `[text](url)` -> `text`.
    while let Some(open) = rest.find("](") {
        let Some(close) = rest[open..].find(')') else { break };
        text.push_str(&rest[..open]);
        rest = &rest[open + close + 1..];
    }
    text.push_str(rest);
    text.trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a markdown file's headings (duplicates get `-1`, `-2`, ... as on GitHub).
fn anchors(text: &str) -> HashSet<String> {
    let mut out = HashSet::new();
    for (_, line) in prose_lines(text) {
        let trimmed = line.trim_start();
        let hashes = trimmed.chars().take_while(|&c| c == '#').count();
        if !(1..=6).contains(&hashes) || !trimmed[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(trimmed[hashes..].trim().trim_end_matches('#'));
        let mut anchor = base.clone();
        let mut n = 0;
        while out.contains(&anchor) {
            n += 1;
            anchor = format!("{base}-{n}");
        }
        out.insert(anchor);
    }
    out
}

/// The targets of the inline links `[text](target)` on one line.
fn link_targets(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = line;
    while let Some(at) = rest.find("](") {
        let after = &rest[at + 2..];
        let Some(end) = after.find(')') else { break };
        // Drop an optional title: `(path "title")`.
        let target = after[..end].split_whitespace().next().unwrap_or("");
        out.push(target.to_string());
        rest = &after[end..];
    }
    out
}

/// The backticked spans of one line.
fn backticked(line: &str) -> Vec<&str> {
    line.split('`').skip(1).step_by(2).collect()
}

/// Prefixes of the repository's top-level folders, resolved from the root.
const ROOT_PREFIXES: [&str; 6] = ["crates/", "docs/", "bench/", "fuzz/", "data/", ".ci/"];

/// The words outside backticks of one line that start with a root folder (`docs/<page>.md`),
/// their trailing punctuation removed.
fn bare_paths(line: &str) -> Vec<&str> {
    let delimiters =
        |c: char| c.is_whitespace() || matches!(c, '(' | ')' | '[' | ']' | '"' | '\'' | ',' | ';');
    line.split('`')
        .step_by(2)
        .flat_map(|outside| outside.split(delimiters))
        .map(|w| w.trim_end_matches(['.', ':', '!', '?']))
        .filter(|w| ROOT_PREFIXES.iter().any(|p| w.starts_with(p)))
        .collect()
}
/// Prefixes resolved inside a crate.
const CRATE_PREFIXES: [&str; 4] = ["tests/", "src/", "examples/", "benches/"];

/// The crate directory a file belongs to (`crates/<name>`), if any.
fn crate_of(root: &Path, file: &Path) -> Option<PathBuf> {
    let rel = file.strip_prefix(root).ok()?;
    let mut parts = rel.components();
    if parts.next()?.as_os_str() != "crates" {
        return None;
    }
    Some(root.join("crates").join(parts.next()?.as_os_str()))
}

/// A checker collecting every failure.
struct Checker {
    root: PathBuf,
    crates: Vec<PathBuf>,
    failures: Vec<String>,
}

impl Checker {
    fn new() -> Self {
        let root = repo_root();
        let mut crates: Vec<PathBuf> = fs::read_dir(root.join("crates"))
            .map(|d| d.flatten().map(|e| e.path()).filter(|p| p.is_dir()).collect())
            .unwrap_or_default();
        crates.sort();
        Self { root, crates, failures: Vec::new() }
    }

    fn where_(&self, file: &Path, line: usize) -> String {
        format!("{}:{line}", file.strip_prefix(&self.root).unwrap_or(file).display())
    }

    /// Check that `path` exists and, for a markdown file, that it has `anchor`.
    fn check_target(&mut self, at: String, shown: &str, path: &Path, anchor: Option<&str>) {
        if !path.exists() {
            self.failures.push(format!("{at}: `{shown}` does not exist"));
            return;
        }
        let Some(anchor) = anchor.filter(|a| !a.is_empty()) else { return };
        if path.extension().is_some_and(|e| e == "md") {
            let text = fs::read_to_string(path).unwrap_or_default();
            if !anchors(&text).contains(anchor) {
                self.failures.push(format!("{at}: `{shown}`: no heading with anchor #{anchor}"));
            }
        }
    }

    /// The relative links of a markdown file.
    fn markdown_links(&mut self, file: &Path, text: &str) {
        let dir = file.parent().unwrap_or(&self.root).to_path_buf();
        for (n, line) in prose_lines(text) {
            for target in link_targets(line) {
                if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
                    continue;
                }
                let (path, anchor) = match target.split_once('#') {
                    Some((p, a)) => (p, Some(a)),
                    None => (target.as_str(), None),
                };
                let resolved = if path.is_empty() { file.to_path_buf() } else { dir.join(path) };
                let at = self.where_(file, n);
                self.check_target(at, &target, &resolved, anchor);
            }
        }
    }

    /// A backticked span that names a repository path, checked.
    fn cited_path(&mut self, file: &Path, n: usize, span: &str) {
        if span.contains(char::is_whitespace)
            || span.contains(['<', '>', '{', '*', '$', '('])
            || span.contains("...")
        {
            return;
        }
        let placeholder =
            |seg: &str| seg.len() > 1 && seg.chars().all(|c| c.is_ascii_uppercase() || c == '_');
        if span.split('/').any(placeholder) {
            return;
        }
        let in_root = ROOT_PREFIXES.iter().any(|p| span.starts_with(p));
        let in_crate = CRATE_PREFIXES.iter().any(|p| span.starts_with(p));
        if !in_root && !in_crate {
            return;
        }
        // `path:line` and `path#anchor`.
        let span = span.split(':').next().unwrap_or(span);
        let (path, anchor) = match span.split_once('#') {
            Some((p, a)) => (p, Some(a)),
            None => (span, None),
        };
        let candidates: Vec<PathBuf> = if in_root {
            vec![self.root.join(path)]
        } else {
            match crate_of(&self.root, file) {
                Some(c) => vec![c.join(path)],
                None => self.crates.iter().map(|c| c.join(path)).collect(),
            }
        };
        let found = candidates.iter().find(|c| c.exists()).cloned();
        let at = self.where_(file, n);
        let resolved = found.unwrap_or_else(|| candidates.first().cloned().unwrap_or_default());
        self.check_target(at, span, &resolved, anchor);
    }

    /// Mentions of the design notes that are not in the repository.
    fn design_notes(&mut self, file: &Path, text: &str) {
        let name = concat!("DESIGN", ".md");
        for (i, line) in text.lines().enumerate() {
            if line.contains(name) {
                let at = self.where_(file, i + 1);
                self.failures.push(format!("{at}: cites {name}, which is not in the repository"));
            }
        }
    }
}

#[test]
fn links_and_cited_paths_resolve() {
    let mut checker = Checker::new();
    let root = checker.root.clone();
    for file in markdown_files(&root) {
        let text = fs::read_to_string(&file).unwrap_or_default();
        checker.markdown_links(&file, &text);
        checker.design_notes(&file, &text);
        for (n, line) in prose_lines(&text) {
            for span in backticked(line).into_iter().chain(bare_paths(line)) {
                checker.cited_path(&file, n, span);
            }
        }
    }
    let mut sources = Vec::new();
    walk(&root.join("crates"), "rs", &mut sources);
    walk(&root.join("fuzz"), "rs", &mut sources);
    assert!(sources.len() > 50, "found only {} .rs files under {}", sources.len(), root.display());
    for file in &sources {
        let text = fs::read_to_string(file).unwrap_or_default();
        checker.design_notes(file, &text);
        for (i, line) in text.lines().enumerate() {
            let Some(comment) = line.trim_start().strip_prefix("//") else { continue };
            for span in backticked(comment).into_iter().chain(bare_paths(comment)) {
                checker.cited_path(file, i + 1, span);
            }
        }
    }
    let mut scripts = Vec::new();
    walk(&root.join("bench"), "py", &mut scripts);
    for file in &scripts {
        let text = fs::read_to_string(file).unwrap_or_default();
        checker.design_notes(file, &text);
        for (i, line) in text.lines().enumerate() {
            for span in backticked(line).into_iter().chain(bare_paths(line)) {
                checker.cited_path(file, i + 1, span);
            }
        }
    }
    // A markdown link's target is also a bare word: one failure each.
    checker.failures.sort();
    checker.failures.dedup();
    assert!(
        checker.failures.is_empty(),
        "{} broken citations:\n{}",
        checker.failures.len(),
        checker.failures.join("\n")
    );
}

#[test]
fn slugs_follow_github() {
    assert_eq!(slug("The default scenario (yorick)"), "the-default-scenario-yorick");
    assert_eq!(
        slug("Self-calibration from any rig motions (`calibrate`)"),
        "self-calibration-from-any-rig-motions-calibrate"
    );
    assert_eq!(slug("0. Verging"), "0-verging");
    assert_eq!(slug("Pan, steering and the drive's motion"), "pan-steering-and-the-drives-motion");
    assert_eq!(slug("fig5-verge-tilt — Verge/tilt alignment"), "fig5-verge-tilt--vergetilt-alignment");
    assert_eq!(slug("A [link](x.md) here"), "a-link-here");
    let a = anchors("# A\n```\n# not a heading\n```\n## A\n");
    assert!(a.contains("a") && a.contains("a-1") && !a.contains("not-a-heading"));
    assert_eq!(link_targets("see [x](a.md#b \"t\") and [y](c/)"), ["a.md#b", "c/"]);
    assert_eq!(
        bare_paths("see docs/a.md. and (bench/b.py), not `docs/c.md` nor xdocs/d"),
        ["docs/a.md", "bench/b.py"]
    );
}
