//! Folder listings keyed by frame number: `12.png` and `000012.txt` are
//! both frame 12.

use super::{ScanError, MAX_FRAMES};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Integer value of a file stem (`000012.png` -> 12).
pub(crate) fn stem_id(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_str()?;
    if stem.is_empty() || !stem.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    stem.parse().ok()
}

/// File stem as text (for frame names).
pub(crate) fn stem(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Path relative to `root` for messages, or the path itself.
pub(crate) fn rel(root: &Path, path: &Path) -> String {
    path.strip_prefix(root).unwrap_or(path).display().to_string()
}

/// Depth PNGs of `root/depth` by frame number; a missing folder means no
/// depth supervision (warned about), not an error.
pub(crate) fn optional_depth_files(
    root: &Path,
    warnings: &mut Vec<String>,
) -> Result<BTreeMap<u64, PathBuf>, ScanError> {
    let depth_dir = root.join("depth");
    if depth_dir.is_dir() {
        files_by_id(&depth_dir, &["png"], warnings)
    } else {
        warnings.push(format!(
            "{}: no depth folder, frames have no depth supervision",
            depth_dir.display()
        ));
        Ok(BTreeMap::new())
    }
}

/// Files of `dir` with one of `exts`, keyed by frame number. Names that are
/// not numbers are skipped with one warning; two files for the same number
/// are an error naming the frame.
pub(crate) fn files_by_id(
    dir: &Path,
    exts: &[&str],
    warnings: &mut Vec<String>,
) -> Result<BTreeMap<u64, PathBuf>, ScanError> {
    let entries = std::fs::read_dir(dir).map_err(|e| ScanError::io(dir, e))?;
    let mut by_id = BTreeMap::new();
    let mut skipped = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| ScanError::io(dir, e))?;
        let path = entry.path();
        let hidden = path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with('.'));
        if hidden || !super::image_io::has_extension(&path, exts) {
            continue;
        }
        // Never open a FIFO (it blocks) or a device; a folder named like a
        // frame file is a mistake worth naming, not a missing frame.
        let meta = std::fs::metadata(&path).map_err(|e| ScanError::io(&path, e))?;
        if meta.is_dir() {
            return Err(ScanError::Invalid(
                path,
                format!("is a directory, expected a .{} file", exts.join("/.")),
            ));
        }
        if !meta.is_file() {
            return Err(ScanError::Invalid(
                path,
                "is not a regular file (a pipe, socket or device); refusing to read it".into(),
            ));
        }
        let Some(id) = stem_id(&path) else {
            skipped.push(
                path.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            );
            continue;
        };
        if let Some(previous) = by_id.insert(id, path.clone()) {
            return Err(ScanError::Frame {
                frame: id.to_string(),
                reason: format!(
                    "two files for the same frame: {} and {}",
                    previous.display(),
                    path.display()
                ),
            });
        }
        if by_id.len() > MAX_FRAMES {
            return Err(ScanError::TooManyFrames {
                path: dir.to_path_buf(),
                count: by_id.len(),
                max: MAX_FRAMES,
            });
        }
    }
    if !skipped.is_empty() {
        skipped.sort();
        let shown: Vec<&str> = skipped.iter().take(3).map(String::as_str).collect();
        warnings.push(format!(
            "{}: {} file(s) whose name is not a frame number were ignored ({}{})",
            dir.display(),
            skipped.len(),
            shown.join(", "),
            if skipped.len() > 3 { ", ..." } else { "" }
        ));
    }
    Ok(by_id)
}

/// Short list of frame ids for messages: `3, 7, 9 and 12 more`.
pub(crate) fn id_list(ids: &[u64]) -> String {
    let shown: Vec<String> = ids.iter().take(5).map(|i| i.to_string()).collect();
    let more = ids.len().saturating_sub(5);
    if more > 0 {
        format!("{} and {more} more", shown.join(", "))
    } else {
        shown.join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stems_pair_by_integer_value() {
        assert_eq!(stem_id(Path::new("rgb/000012.png")), Some(12));
        assert_eq!(stem_id(Path::new("12.txt")), Some(12));
        assert_eq!(stem_id(Path::new("frame_1.png")), None);
        assert_eq!(stem_id(Path::new("-1.png")), None);
        assert_eq!(stem_id(Path::new("99999999999999999999999.png")), None);
    }

    #[test]
    fn listing_skips_non_numbers_and_rejects_duplicates() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["000001.png", "2.jpg", "notes.png", "3.txt", ".hidden.png"] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        let mut warnings = Vec::new();
        let found = files_by_id(dir.path(), &["png", "jpg"], &mut warnings).unwrap();
        assert_eq!(found.keys().copied().collect::<Vec<_>>(), vec![1, 2]);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].contains("notes.png"));
        std::fs::write(dir.path().join("01.png"), b"x").unwrap();
        let err = files_by_id(dir.path(), &["png", "jpg"], &mut warnings)
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("frame 1: two files"), "{err}");
    }

    #[test]
    fn id_lists_are_short() {
        assert_eq!(id_list(&[1, 2]), "1, 2");
        assert_eq!(id_list(&[1, 2, 3, 4, 5, 6, 7]), "1, 2, 3, 4, 5 and 2 more");
    }
}
