//! The manifest: JSON Lines, one scan a line. Relative paths are taken from
//! the manifest's folder; every line is checked before any work, and a
//! problem names the line and the field.

use super::error::BatchError;
use crate::nerf::train::settings::Preset;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Most scans one manifest may list.
pub const MAX_ENTRIES: usize = 1_000_000;
/// Longest accepted manifest line, bytes.
const MAX_LINE: usize = 64 * 1024;
/// Synthetic views per scan when a line does not say (as `synth --n`).
pub const DEFAULT_SYNTH_VIEWS: usize = 500;
/// Most synthetic views one line may ask for.
const MAX_SYNTH_VIEWS: usize = 1_000_000;

/// One manifest line as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Line {
    scan: PathBuf,
    id: Option<String>,
    boxes: Option<PathBuf>,
    masks: Option<PathBuf>,
    time: Option<f64>,
    steps: Option<u64>,
    seed: Option<u64>,
    preset: Option<Preset>,
    synth_views: Option<usize>,
    synth_width: Option<u32>,
    synth_height: Option<u32>,
}

/// One scan of the manifest, paths resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    /// 0-based position among the manifest's scans (the array task index).
    pub index: usize,
    /// 1-based line of the manifest, for messages.
    pub line: usize,
    /// Name of the scan in merged outputs (`scan=<id>`): unique, file-name safe.
    pub id: String,
    pub scan: PathBuf,
    pub boxes: Option<PathBuf>,
    pub masks: Option<PathBuf>,
    /// Fit wall-time budget, seconds (`fit --time`).
    pub time: Option<f64>,
    /// Fit step budget (`fit --steps`).
    pub steps: Option<u64>,
    pub seed: u64,
    pub preset: Preset,
    /// Synthetic views to render; 0 skips synth.
    pub synth_views: usize,
    pub synth_width: Option<u32>,
    pub synth_height: Option<u32>,
}

impl Entry {
    /// SCAN/nerflabel, where the scan's outputs and batch status go.
    pub fn work_dir(&self) -> PathBuf {
        self.scan.join("nerflabel")
    }
    /// Whether the scan is labelled (it has boxes or masks).
    pub fn labels(&self) -> bool {
        self.boxes.is_some() || self.masks.is_some()
    }
}

/// A checked manifest.
#[derive(Clone, Debug)]
pub struct Manifest {
    pub path: PathBuf,
    pub entries: Vec<Entry>,
}

/// Read and check a manifest.
pub fn read_manifest(path: &Path) -> Result<Manifest, BatchError> {
    let text = std::fs::read_to_string(path).map_err(|source| BatchError::ReadManifest {
        path: path.to_path_buf(),
        source,
    })?;
    let base = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    parse_manifest(&text, path, base)
}

/// Parse manifest `text` (read from `path`; relative paths from `base`).
pub fn parse_manifest(text: &str, path: &Path, base: &Path) -> Result<Manifest, BatchError> {
    let err = |line: usize, problem: String| BatchError::Manifest {
        path: path.to_path_buf(),
        line,
        problem,
    };
    let mut entries: Vec<Entry> = Vec::new();
    let mut ids: BTreeMap<String, usize> = BTreeMap::new();
    for (n, raw) in text.lines().enumerate() {
        let line = n + 1;
        if raw.trim().is_empty() {
            continue;
        }
        if entries.len() >= MAX_ENTRIES {
            return Err(BatchError::TooManyEntries {
                path: path.to_path_buf(),
                max: MAX_ENTRIES,
            });
        }
        if raw.len() > MAX_LINE {
            return Err(err(line, format!("longer than {MAX_LINE} bytes")));
        }
        let parsed: Line = serde_json::from_str(raw).map_err(|e| err(line, json_problem(&e)))?;
        let entry = check_line(parsed, entries.len(), line, base).map_err(|p| err(line, p))?;
        if let Some(first) = ids.insert(entry.id.clone(), line) {
            return Err(err(
                line,
                format!(
                    "`id`: `{}` is already the id of line {first} (ids name the merged partitions: give each scan its own)",
                    entry.id
                ),
            ));
        }
        entries.push(entry);
    }
    if entries.is_empty() {
        return Err(BatchError::EmptyManifest {
            path: path.to_path_buf(),
        });
    }
    Ok(Manifest {
        path: path.to_path_buf(),
        entries,
    })
}

/// serde_json's message, with "unknown field" pointed at the fields there are.
fn json_problem(e: &serde_json::Error) -> String {
    let message = e.to_string();
    if message.contains("unknown field") || message.contains("missing field") {
        // serde_json lists the expected fields itself; drop its position suffix.
        return message.split(" at line ").next().unwrap_or(&message).to_string();
    }
    format!("not a JSON object of a scan ({message})")
}

fn check_line(l: Line, index: usize, line: usize, base: &Path) -> Result<Entry, String> {
    if l.scan.as_os_str().is_empty() {
        return Err("`scan`: empty path".into());
    }
    let resolve = |p: PathBuf| if p.is_absolute() { p } else { base.join(p) };
    let scan = resolve(l.scan);
    let id = match l.id {
        Some(id) => id,
        None => default_id(&scan).ok_or_else(|| {
            format!(
                "`scan`: {} has no folder name to take the id from; give `id`",
                scan.display()
            )
        })?,
    };
    check_id(&id).map_err(|p| format!("`id`: `{id}` {p}"))?;
    if let Some(t) = l.time {
        if !(t > 0.0 && t.is_finite()) {
            return Err(format!("`time`: {t} is not a positive number of seconds"));
        }
    }
    if l.steps == Some(0) {
        return Err("`steps`: 0 trains nothing; give at least 1 or leave it out".into());
    }
    let synth_views = l.synth_views.unwrap_or(DEFAULT_SYNTH_VIEWS);
    if synth_views > MAX_SYNTH_VIEWS {
        return Err(format!("`synth_views`: {synth_views} is more than {MAX_SYNTH_VIEWS}"));
    }
    for (name, side) in [("synth_width", l.synth_width), ("synth_height", l.synth_height)] {
        if side == Some(0) {
            return Err(format!("`{name}`: 0 pixels"));
        }
    }
    Ok(Entry {
        index,
        line,
        id,
        scan,
        boxes: l.boxes.map(resolve),
        masks: l.masks.map(resolve),
        time: l.time,
        steps: l.steps,
        seed: l.seed.unwrap_or(0),
        preset: l.preset.unwrap_or(Preset::Default),
        synth_views,
        synth_width: l.synth_width,
        synth_height: l.synth_height,
    })
}

/// The scan folder's name (of the path as given, `..` resolved).
fn default_id(scan: &Path) -> Option<String> {
    let resolved = crate::outputs::resolve(scan);
    resolved.file_name().map(|n| n.to_string_lossy().into_owned())
}

/// Ids become folder names (`scan=<id>`) and column values: letters,
/// digits, `.`, `_`, `-`, not starting with `.`, at most 128 bytes.
fn check_id(id: &str) -> Result<(), &'static str> {
    if id.is_empty() || id.len() > 128 {
        return Err("must be 1 to 128 characters");
    }
    if id.starts_with('.') {
        return Err("must not start with `.`");
    }
    if !id
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
    {
        return Err("may hold only letters, digits, `.`, `_` and `-` (it names a folder `scan=<id>`)");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Manifest, String> {
        parse_manifest(text, Path::new("m.jsonl"), Path::new("/data")).map_err(|e| e.to_string())
    }

    #[test]
    fn lines_resolve_from_the_manifest_folder_and_take_defaults() {
        let m = parse(
            "{\"scan\": \"scans/kitchen\", \"boxes\": \"b.json\", \"time\": 30}\n\n{\"scan\": \"/abs/desk\", \"id\": \"d-1\", \"synth_views\": 0, \"preset\": \"fast\"}\n",
        )
        .unwrap();
        assert_eq!(m.entries.len(), 2);
        let (a, b) = (&m.entries[0], &m.entries[1]);
        assert_eq!((a.index, a.line, a.id.as_str()), (0, 1, "kitchen"));
        assert_eq!(a.scan, Path::new("/data/scans/kitchen"));
        assert_eq!(a.boxes.as_deref(), Some(Path::new("/data/b.json")));
        assert_eq!(
            (a.time, a.synth_views, a.preset),
            (Some(30.0), DEFAULT_SYNTH_VIEWS, Preset::Default)
        );
        assert_eq!((b.index, b.line, b.id.as_str()), (1, 3, "d-1"));
        assert_eq!(
            (b.scan.as_path(), b.synth_views, b.preset),
            (Path::new("/abs/desk"), 0, Preset::Fast)
        );
        assert!(a.labels() && !b.labels());
    }

    #[test]
    fn problems_name_the_line_and_the_field() {
        let e = parse("{\"scan\": \"a\"}\n{\"scan\": \"b\", \"tme\": 3}").unwrap_err();
        assert!(e.contains("m.jsonl line 2") && e.contains("unknown field `tme`"), "{e}");
        let e = parse("{\"boxes\": \"b.json\"}").unwrap_err();
        assert!(e.contains("line 1") && e.contains("missing field `scan`"), "{e}");
        let e = parse("{\"scan\": \"a\", \"time\": -1}").unwrap_err();
        assert!(e.contains("line 1") && e.contains("`time`"), "{e}");
        let e = parse("{\"scan\": \"x/a\"}\n{\"scan\": \"y/a\"}").unwrap_err();
        assert!(e.contains("line 2") && e.contains("already the id of line 1"), "{e}");
        let e = parse("{\"scan\": \"a\", \"id\": \"a/b\"}").unwrap_err();
        assert!(e.contains("`id`: `a/b`"), "{e}");
        let e = parse("{\"scan\": \"a\", \"preset\": \"turbo\"}").unwrap_err();
        assert!(e.contains("line 1") && e.contains("turbo"), "{e}");
        let e = parse("not json").unwrap_err();
        assert!(e.contains("line 1: not a JSON object"), "{e}");
        let e = parse("\n \n").unwrap_err();
        assert!(e.contains("lists no scans"), "{e}");
    }
}
