//! Output paths are checked before any work starts: an output never is,
//! contains or lies inside a scan's input folders or files, never replaces
//! a directory with a file (or the reverse), never lies under a regular
//! file, and the outputs of one command never coincide.

use crate::scan::Scan;
use std::collections::BTreeSet;
use std::path::{Component, Path, PathBuf};

/// Why an output path cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("{path}: refusing to write {what} there: it would overwrite the scan's input {input}")]
    OverInput {
        path: PathBuf,
        what: String,
        input: PathBuf,
    },
    #[error("{path}: refusing to write {what} there: it lies inside the scan's input folder {input}")]
    InsideInput {
        path: PathBuf,
        what: String,
        input: PathBuf,
    },
    #[error("{path}: refusing to write {what} there: it contains the scan's input {input}")]
    ContainsInput {
        path: PathBuf,
        what: String,
        input: PathBuf,
    },
    #[error("{path}: is a directory, expected a file path for {what}")]
    IsDirectory { path: PathBuf, what: String },
    #[error("{path}: is a file, expected a folder for {what}")]
    IsFile { path: PathBuf, what: String },
    #[error("{path}: cannot write {what}: {parent} is a file, not a folder")]
    UnderFile {
        path: PathBuf,
        what: String,
        parent: PathBuf,
    },
    #[error("{path}: {first} and {second} would be written to the same file")]
    SamePath {
        path: PathBuf,
        first: String,
        second: String,
    },
    #[error(
        "{path}: another nerflabel process{holder} is writing {what}; wait for it to finish or choose another path"
    )]
    Locked {
        path: PathBuf,
        what: String,
        holder: String,
    },
    #[error("{path}: cannot lock {what}: {source}")]
    Lock {
        path: PathBuf,
        what: String,
        source: std::io::Error,
    },
}

/// An exclusive lock on an output, held until dropped. The operating
/// system releases it when the process ends, however it ends, so a killed
/// run never leaves a stale lock.
#[derive(Debug)]
pub struct OutputLock {
    _file: std::fs::File,
}

/// Lock `target` (a file or folder that may not exist yet) through the
/// hidden file `.NAME.lock` beside it; a second process fails at once with
/// the first one's pid.
pub fn lock_output(target: &Path, what: &str) -> Result<OutputLock, OutputError> {
    use std::io::{Read, Seek, Write};
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let path = target.with_file_name(format!(".{name}.lock"));
    let lock_err = |source| OutputError::Lock {
        path: path.clone(),
        what: what.to_string(),
        source,
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(lock_err)?;
    }
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(lock_err)?;
    match file.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            let mut pid = String::new();
            let _ = file.read_to_string(&mut pid);
            let pid = pid.trim();
            let holder = if pid.is_empty() {
                String::new()
            } else {
                format!(" (pid {pid})")
            };
            return Err(OutputError::Locked {
                path: target.to_path_buf(),
                what: what.to_string(),
                holder,
            });
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(lock_err(e)),
    }
    // The pid is only for the message a second process prints.
    let _ = file
        .set_len(0)
        .and_then(|_| file.rewind())
        .and_then(|_| write!(file, "{}", std::process::id()));
    Ok(OutputLock { _file: file })
}

/// Whether an output is one file or a folder of files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputKind {
    File,
    Folder,
}

/// One output of a command: where, what it is, and a name for messages.
#[derive(Clone, Debug)]
pub struct Output<'a> {
    pub path: &'a Path,
    pub kind: OutputKind,
    pub what: &'a str,
}

impl<'a> Output<'a> {
    pub fn file(path: &'a Path, what: &'a str) -> Self {
        Output {
            path,
            kind: OutputKind::File,
            what,
        }
    }
    pub fn folder(path: &'a Path, what: &'a str) -> Self {
        Output {
            path,
            kind: OutputKind::Folder,
            what,
        }
    }
}

/// What of a scan no output may touch: folders holding per-frame inputs
/// (protected whole) and single files at the scan root.
#[derive(Clone, Debug, Default)]
pub struct ProtectedInputs {
    folders: BTreeSet<PathBuf>,
    files: BTreeSet<PathBuf>,
}

impl ProtectedInputs {
    /// The inputs of `scan`: a folder input is protected whole, a file in a
    /// sub-folder protects that folder (new files there would be read as
    /// frames next time), a file at the root protects itself.
    pub fn of(scan: &Scan) -> ProtectedInputs {
        let root = resolve(&scan.root);
        let mut protected = ProtectedInputs::default();
        for input in &scan.inputs {
            let path = resolve(input);
            if path.is_dir() {
                protected.folders.insert(path);
            } else {
                match path.parent() {
                    Some(parent) if parent != root => protected.folders.insert(parent.to_path_buf()),
                    _ => protected.files.insert(path),
                };
            }
        }
        protected
    }
}

/// Check the outputs of one command against each other, the file system and
/// the scan's inputs (`None` when the command reads no scan).
pub fn check_outputs(outputs: &[Output], inputs: Option<&ProtectedInputs>) -> Result<(), OutputError> {
    let resolved: Vec<PathBuf> = outputs.iter().map(|o| resolve(o.path)).collect();
    for (i, output) in outputs.iter().enumerate() {
        for (j, other) in outputs.iter().enumerate().skip(i + 1) {
            if resolved[i] == resolved[j] {
                return Err(OutputError::SamePath {
                    path: output.path.to_path_buf(),
                    first: output.what.to_string(),
                    second: other.what.to_string(),
                });
            }
        }
        check_file_system(output)?;
        if let Some(inputs) = inputs {
            check_against_inputs(output, &resolved[i], inputs)?;
        }
    }
    Ok(())
}

fn check_file_system(output: &Output) -> Result<(), OutputError> {
    let (path, what) = (output.path.to_path_buf(), output.what.to_string());
    match output.kind {
        OutputKind::File if output.path.is_dir() => return Err(OutputError::IsDirectory { path, what }),
        OutputKind::Folder if output.path.exists() && !output.path.is_dir() => {
            return Err(OutputError::IsFile { path, what })
        }
        _ => {}
    }
    let mut ancestor = output.path.parent();
    while let Some(dir) = ancestor {
        if dir.exists() {
            if !dir.is_dir() {
                return Err(OutputError::UnderFile {
                    path,
                    what,
                    parent: dir.to_path_buf(),
                });
            }
            break;
        }
        ancestor = dir.parent();
    }
    Ok(())
}

fn check_against_inputs(output: &Output, resolved: &Path, inputs: &ProtectedInputs) -> Result<(), OutputError> {
    let err_path = output.path.to_path_buf();
    let what = output.what.to_string();
    for folder in &inputs.folders {
        if resolved == folder {
            return Err(OutputError::OverInput {
                path: err_path,
                what,
                input: folder.clone(),
            });
        }
        if resolved.starts_with(folder) {
            return Err(OutputError::InsideInput {
                path: err_path,
                what,
                input: folder.clone(),
            });
        }
        if folder.starts_with(resolved) {
            return Err(OutputError::ContainsInput {
                path: err_path,
                what,
                input: folder.clone(),
            });
        }
    }
    for file in &inputs.files {
        if resolved == file {
            return Err(OutputError::OverInput {
                path: err_path,
                what,
                input: file.clone(),
            });
        }
        if file.starts_with(resolved) {
            return Err(OutputError::ContainsInput {
                path: err_path,
                what,
                input: file.clone(),
            });
        }
    }
    Ok(())
}

/// Absolute path with symlinks of its existing part resolved and `.`/`..`
/// of the rest applied as the file system would, so two spellings of one
/// place compare equal.
pub fn resolve(path: &Path) -> PathBuf {
    let absolute = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir()
            .map(|d| d.join(path))
            .unwrap_or_else(|_| path.to_path_buf())
    };
    let mut out = PathBuf::new();
    for component in absolute.components() {
        match component {
            Component::Prefix(_) | Component::RootDir => out.push(component.as_os_str()),
            Component::CurDir => {}
            Component::ParentDir => match out.join("..").canonicalize() {
                Ok(parent) if out.exists() => out = parent,
                _ => {
                    out.pop();
                }
            },
            Component::Normal(name) => {
                out.push(name);
                if let Ok(canonical) = out.canonicalize() {
                    out = canonical;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn protected(root: &Path) -> ProtectedInputs {
        let mut p = ProtectedInputs::default();
        p.folders.insert(resolve(&root.join("rgb")));
        p.files.insert(resolve(&root.join("intrinsics.txt")));
        p
    }

    #[test]
    fn outputs_over_inside_or_around_inputs_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("scan");
        std::fs::create_dir_all(root.join("rgb")).unwrap();
        std::fs::write(root.join("intrinsics.txt"), "k").unwrap();
        let inputs = protected(&root);
        let refused = |path: PathBuf, kind| {
            check_outputs(
                &[Output {
                    path: &path,
                    kind,
                    what: "x",
                }],
                Some(&inputs),
            )
            .is_err()
        };
        assert!(refused(root.clone(), OutputKind::Folder), "scan root contains inputs");
        assert!(refused(root.join("rgb"), OutputKind::Folder));
        assert!(refused(root.join("rgb/new"), OutputKind::Folder));
        assert!(refused(root.join("rgb/000000.png"), OutputKind::File));
        assert!(refused(root.join("intrinsics.txt"), OutputKind::File));
        assert!(
            refused(root.join("nerflabel/../rgb/x.nlf"), OutputKind::File),
            "`..` is resolved"
        );
        let ok = |path: PathBuf, kind| {
            check_outputs(
                &[Output {
                    path: &path,
                    kind,
                    what: "x",
                }],
                Some(&inputs),
            )
            .is_ok()
        };
        assert!(ok(root.join("nerflabel/labels"), OutputKind::Folder));
        assert!(ok(root.join("nerflabel/model.nlf"), OutputKind::File));
        assert!(ok(root.join("labels"), OutputKind::Folder));
    }

    #[test]
    fn a_second_lock_on_one_output_fails_naming_the_holder_and_is_free_after_drop() {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("model.nlf");
        let first = lock_output(&model, "the model").unwrap();
        let err = lock_output(&model, "the model").unwrap_err().to_string();
        assert!(
            err.contains(&format!("pid {}", std::process::id())) && err.contains("model.nlf"),
            "{err}"
        );
        drop(first);
        lock_output(&model, "the model").expect("free again once the holder is gone");
    }

    #[test]
    fn directory_for_a_file_file_for_a_folder_path_under_a_file_and_twins_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("f.txt");
        std::fs::write(&file, "x").unwrap();
        let one = |o: Output| check_outputs(&[o], None).map_err(|e| e.to_string());
        assert!(one(Output::file(dir.path(), "the model"))
            .unwrap_err()
            .contains("is a directory"));
        assert!(one(Output::folder(&file, "labels")).unwrap_err().contains("is a file"));
        let under = file.join("sub/model.nlf");
        assert!(one(Output::file(&under, "the model"))
            .unwrap_err()
            .contains("is a file, not a folder"));
        let same = dir.path().join("a.json");
        let twin = dir.path().join("./a.json");
        let err = check_outputs(
            &[Output::file(&same, "the model"), Output::file(&twin, "the report")],
            None,
        )
        .unwrap_err();
        assert!(err.to_string().contains("the model and the report"), "{err}");
    }
}
