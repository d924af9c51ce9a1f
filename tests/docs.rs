//! The repository stands alone: every file or image a Markdown page links exists in it,
//! and no source, test or document reaches outside it for files.

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every file below `dir` with one of `extensions`, skipping build output and hidden
/// folders.
fn files_with(dir: &Path, extensions: &[&str], found: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if path.is_dir() {
            if !name.starts_with('.') && !["target", "corpus", "artifacts"].contains(&&*name) {
                files_with(&path, extensions, found);
            }
        } else if path
            .extension()
            .is_some_and(|e| extensions.contains(&&*e.to_string_lossy()))
        {
            found.push(path);
        }
    }
}

/// The targets of inline Markdown links and images, `[text](target)`, outside code.
fn link_targets(markdown: &str) -> Vec<String> {
    let mut targets = Vec::new();
    let mut in_fence = false;
    for line in markdown.lines() {
        if line.trim_start().starts_with("```") {
            in_fence = !in_fence;
            continue;
        }
        if in_fence {
            continue;
        }
        // Inline code spans may show link syntax as text.
        let prose: String = line.split('`').step_by(2).collect::<Vec<_>>().join(" ");
        let mut rest = prose.as_str();
        while let Some(start) = rest.find("](") {
            let after = &rest[start + 2..];
            let Some(end) = after.find(')') else { break };
            let target = after[..end].split_whitespace().next().unwrap_or("");
            targets.push(target.trim_matches(['"', '<', '>']).to_string());
            rest = &after[end..];
        }
    }
    targets
}

fn is_local(target: &str) -> bool {
    !(target.is_empty()
        || target.starts_with('#')
        || target.contains("://")
        || target.starts_with("mailto:"))
}

#[test]
fn every_file_a_markdown_page_links_exists() {
    let mut pages = Vec::new();
    files_with(&root(), &["md"], &mut pages);
    assert!(pages.len() >= 4, "found only {pages:?}");
    let mut broken = Vec::new();
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        for target in link_targets(&text).into_iter().filter(|t| is_local(t)) {
            let file = target.split('#').next().unwrap_or_default();
            let resolved = page.parent().unwrap().join(file);
            let inside = resolved
                .canonicalize()
                .is_ok_and(|p| p.starts_with(root().canonicalize().unwrap()));
            if !inside {
                broken.push(format!("{}: {target}", page.display()));
            }
        }
    }
    assert!(
        broken.is_empty(),
        "links to files missing from the repository:\n{}",
        broken.join("\n")
    );
}

#[test]
fn link_targets_are_found_in_prose_and_not_in_code() {
    let page = "see [a](a.md) and ![plot](img/p.png \"title\")\n`[x](code.md)`\n```\n[y](fenced.md)\n```\n[web](https://x.org)";
    let targets = link_targets(page);
    assert_eq!(targets, ["a.md", "img/p.png", "https://x.org"]);
    assert!(!is_local("https://x.org") && !is_local("#section") && is_local("a.md"));
}

#[test]
fn nothing_reads_files_beside_the_repository() {
    // A user's clone has nothing beside it; CI does (`shared/`), so only this catches it.
    let needle = concat!("..", "/shared");
    let mut files = Vec::new();
    files_with(&root(), &["rs", "toml", "md", "sh"], &mut files);
    files.push(root().join(".ci/run"));
    let offenders: Vec<_> = files
        .iter()
        .filter(|f| std::fs::read_to_string(f).is_ok_and(|text| text.contains(needle)))
        .map(|f| f.display().to_string())
        .collect();
    assert!(offenders.is_empty(), "files naming {needle}: {offenders:?}");
}
