//! The house's floors (issue 32): no import circle between the crate's modules, at the
//! level of the top-level modules (`bench`, `sim`, `model`, ...) and of their children
//! (`bench::journal`, `bench::integrity`, ...). A module's imports are the
//! `crate::a::b` and `super::x` paths in its code (comments and `#[cfg(test)]` parts
//! left out: a doc link or a test helper is not a floor).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use crate::util::root;

/// Module path (`bench::journal`) -> its source, outside comments and tests.
fn sources(dir: &Path, prefix: &[String], out: &mut BTreeMap<Vec<String>, String>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_stem().unwrap().to_string_lossy().to_string();
        if path.is_dir() {
            let mut p = prefix.to_vec();
            p.push(name);
            sources(&path, &p, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            let mut p = prefix.to_vec();
            if !["mod", "lib", "main"].contains(&name.as_str()) {
                p.push(name);
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap_or("");
            let code: String = code
                .lines()
                .filter(|l| !l.trim_start().starts_with("//"))
                .collect::<Vec<_>>()
                .join("\n");
            out.entry(p).or_default().push_str(&code);
        }
    }
}

/// The identifiers of a `::`-path starting right after `at` in `s`.
fn path_after(s: &str) -> Vec<String> {
    let mut parts = Vec::new();
    let mut rest = s;
    loop {
        let n = rest
            .find(|c: char| !(c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_'))
            .unwrap_or(rest.len());
        if n == 0 {
            break;
        }
        parts.push(rest[..n].to_string());
        match rest[n..].strip_prefix("::") {
            Some(r) => rest = r,
            None => break,
        }
    }
    parts
}

/// The module graph cut at `level` path components.
fn graph(level: usize) -> BTreeMap<Vec<String>, BTreeSet<Vec<String>>> {
    let mut src = BTreeMap::new();
    sources(&root("src"), &[], &mut src);
    let cut = |p: &[String]| p[..p.len().min(level)].to_vec();
    let known: BTreeSet<Vec<String>> = src
        .keys()
        .filter(|k| !k.is_empty())
        .map(|k| cut(k))
        .collect();
    let mut g: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for (module, code) in &src {
        if module.is_empty() {
            continue;
        }
        let from = cut(module);
        let mut targets = Vec::new();
        for (i, _) in code.match_indices("crate::") {
            targets.push(path_after(&code[i + 7..]));
        }
        for (i, _) in code.match_indices("super::") {
            if code[..i].ends_with("::") {
                continue;
            }
            let mut p = module[..module.len() - 1].to_vec();
            p.extend(path_after(&code[i + 7..]).into_iter().take(1));
            targets.push(p);
        }
        let set = g.entry(from.clone()).or_default();
        for t in targets {
            let t = cut(&t);
            if t != from && known.contains(&t) {
                set.insert(t);
            }
        }
    }
    g
}

/// A circle through `start` in `g`, if any (depth-first search).
fn circle(
    g: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
    start: &Vec<String>,
) -> Option<Vec<String>> {
    let mut stack = vec![(start.clone(), vec![start.join("::")])];
    let mut seen = BTreeSet::new();
    while let Some((node, trail)) = stack.pop() {
        for next in g.get(&node).into_iter().flatten() {
            if next == start {
                let mut t = trail.clone();
                t.push(start.join("::"));
                return Some(t);
            }
            if seen.insert(next.clone()) {
                let mut t = trail.clone();
                t.push(next.join("::"));
                stack.push((next.clone(), t));
            }
        }
    }
    None
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    for level in [1, 2] {
        let g = graph(level);
        assert!(
            g.len() > 10,
            "the source tree was read: {} modules",
            g.len()
        );
        let circles: Vec<String> = g
            .keys()
            .filter_map(|m| circle(&g, m))
            .map(|c| c.join(" -> "))
            .collect();
        assert!(
            circles.is_empty(),
            "import circles at depth {level}: {circles:#?}"
        );
    }
}
