//! The container shared by the model file and the training checkpoint:
//! 8 magic bytes, u32 version, u32 header length, JSON header, sections of
//! little-endian f32s or u64 words, and a CRC32 of everything before it.
//! Written atomically; read with caps on header and file size, and every
//! defect is a `ContainerError` the caller names its file in.

use serde::de::DeserializeOwned;
use std::io::{self, Write};
use std::path::Path;

/// Offsets of the version and the header length, after the magic.
const VERSION_AT: usize = 8;
const HEADER_LEN_AT: usize = 12;
/// Bytes before the header JSON: magic, version, header length.
const PREAMBLE: usize = 16;
/// Bytes of the trailing CRC32.
const CRC_LEN: usize = 4;
/// Values encoded per buffered write.
const CHUNK: usize = 16384;

/// What distinguishes one kind of file in this container.
pub struct Format {
    pub magic: &'static [u8; 8],
    pub version: u32,
    /// Header JSON larger than this is rejected.
    pub max_header: usize,
    /// Files larger than this are rejected before reading.
    pub max_file: u64,
    /// What one file is called in errors ("model").
    pub name: &'static str,
    /// What its sections hold, in errors ("parameters").
    pub contents: &'static str,
}

/// One section to write.
#[derive(Clone, Copy)]
pub enum Section<'a> {
    F32(&'a [f32]),
    U64(&'a [u64]),
}

impl Section<'_> {
    /// Number of values (what the header records).
    pub fn count(&self) -> usize {
        match self {
            Section::F32(values) => values.len(),
            Section::U64(words) => words.len(),
        }
    }
}

/// Element type of a section to read.
#[derive(Clone, Copy)]
pub enum SectionKind {
    F32,
    U64,
}

impl SectionKind {
    fn bytes(self) -> usize {
        match self {
            SectionKind::F32 => 4,
            SectionKind::U64 => 8,
        }
    }
}

/// The bytes of one section read, its size already checked.
#[derive(Clone, Copy)]
pub struct SectionBytes<'a>(&'a [u8]);

impl SectionBytes<'_> {
    /// The values of a `SectionKind::F32` section.
    pub fn f32s(self) -> Vec<f32> {
        self.0
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }

    /// The words of a `SectionKind::U64` section.
    pub fn u64s(self) -> Vec<u64> {
        self.0
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect()
    }
}

/// Why a container could not be read; the caller adds the path.
#[derive(Debug, thiserror::Error)]
pub enum ContainerError {
    /// The file's metadata could not be read (a missing file is `NotFound`).
    #[error("cannot open: {0}")]
    Open(io::Error),
    #[error("cannot read: {0}")]
    Read(io::Error),
    #[error("wrong magic bytes")]
    Magic,
    #[error("format version {0} is not supported")]
    Version(u32),
    #[error("checksum mismatch")]
    Checksum,
    #[error("{0}")]
    Damaged(String),
}

/// Writer that keeps a CRC32 of everything written.
struct CrcWriter<'a, W: Write> {
    inner: &'a mut W,
    crc: crc32fast::Hasher,
}

impl<W: Write> Write for CrcWriter<'_, W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(buf.get(..n).unwrap_or(buf));
        Ok(n)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// Write values little-endian through a bounded buffer.
fn write_values<W: Write, T: Copy, const N: usize>(w: &mut W, values: &[T], to_le: fn(T) -> [u8; N]) -> io::Result<()> {
    let mut buf = Vec::with_capacity(N * CHUNK.min(values.len()));
    for chunk in values.chunks(CHUNK) {
        buf.clear();
        chunk.iter().for_each(|&v| buf.extend_from_slice(&to_le(v)));
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Write a whole container to `w`; `header_json` already records the
/// section lengths.
pub fn write<W: Write>(w: &mut W, format: &Format, header_json: &[u8], sections: &[Section]) -> io::Result<()> {
    let header_len = u32::try_from(header_json.len()).map_err(|_| {
        io::Error::other(format!(
            "a header of {} bytes does not fit the format",
            header_json.len()
        ))
    })?;
    let mut body = CrcWriter {
        inner: w,
        crc: crc32fast::Hasher::new(),
    };
    body.write_all(format.magic)?;
    body.write_all(&format.version.to_le_bytes())?;
    body.write_all(&header_len.to_le_bytes())?;
    body.write_all(header_json)?;
    for section in sections {
        match *section {
            Section::F32(values) => write_values(&mut body, values, f32::to_le_bytes)?,
            Section::U64(words) => write_values(&mut body, words, u64::to_le_bytes)?,
        }
    }
    let crc = body.crc.finalize();
    w.write_all(&crc.to_le_bytes())
}

/// Write a container to `path` atomically (temp file + rename).
pub fn save(path: &Path, format: &Format, header_json: &[u8], sections: &[Section]) -> io::Result<()> {
    crate::atomic::write_with(path, |file| write(file, format, header_json, sections))
}

/// Read a whole file, refusing one larger than `format.max_file`.
pub fn read(path: &Path, format: &Format) -> Result<Vec<u8>, ContainerError> {
    let size = std::fs::metadata(path).map_err(ContainerError::Open)?.len();
    if size > format.max_file {
        return Err(ContainerError::Damaged(format!(
            "{size} bytes is larger than any {}",
            format.name
        )));
    }
    std::fs::read(path).map_err(ContainerError::Read)
}

fn le_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let end = at.checked_add(4)?;
    let b = bytes.get(at..end)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// Verify `bytes` (magic, version, checksum, header, section sizes) and
/// split them into the header and its sections, whose kinds are `kinds`
/// and whose lengths the header records (`lengths`).
pub fn decode<'a, H: DeserializeOwned, const N: usize>(
    bytes: &'a [u8],
    format: &Format,
    kinds: &[SectionKind; N],
    lengths: impl FnOnce(&H) -> [usize; N],
) -> Result<(H, [SectionBytes<'a>; N]), ContainerError> {
    let damaged = ContainerError::Damaged;
    if bytes.get(..format.magic.len()) != Some(format.magic.as_slice()) {
        return Err(ContainerError::Magic);
    }
    let crc_at = bytes.len().checked_sub(CRC_LEN).filter(|&at| at >= PREAMBLE);
    let (Some(version), Some(header_len), Some(crc_at)) =
        (le_u32(bytes, VERSION_AT), le_u32(bytes, HEADER_LEN_AT), crc_at)
    else {
        return Err(damaged("truncated header".into()));
    };
    if version != format.version {
        return Err(ContainerError::Version(version));
    }
    let (body, stored) = bytes.split_at(crc_at);
    if le_u32(stored, 0) != Some(crc32fast::hash(body)) {
        return Err(ContainerError::Checksum);
    }
    let header_end = usize::try_from(header_len)
        .ok()
        .filter(|&n| n <= format.max_header)
        .and_then(|n| n.checked_add(PREAMBLE))
        .filter(|&end| end <= body.len())
        .ok_or_else(|| damaged(format!("header length {header_len} does not fit the file")))?;
    let (preamble_and_json, data) = body.split_at(header_end);
    let json = preamble_and_json.get(PREAMBLE..).unwrap_or_default();
    let header: H = serde_json::from_slice(json).map_err(|e| damaged(format!("header is not valid: {e}")))?;
    let lengths = lengths(&header);
    let overflow = || damaged("section sizes overflow".into());
    let mut sizes = [0usize; N];
    let mut needed = 0usize;
    for ((size, &n), kind) in sizes.iter_mut().zip(&lengths).zip(kinds) {
        *size = n.checked_mul(kind.bytes()).ok_or_else(overflow)?;
        needed = needed.checked_add(*size).ok_or_else(overflow)?;
    }
    if needed != data.len() {
        return Err(damaged(format!(
            "expected {needed} bytes of {}, found {}",
            format.contents,
            data.len()
        )));
    }
    let mut sections = [SectionBytes(&[]); N];
    let mut rest = data;
    for (section, size) in sections.iter_mut().zip(sizes) {
        // Sizes add up to the data's length, so every split fits.
        let (head, tail) = rest.split_at_checked(size).unwrap_or((rest, &[]));
        *section = SectionBytes(head);
        rest = tail;
    }
    Ok((header, sections))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::{Deserialize, Serialize};

    const TEST: Format = Format {
        magic: b"NLFTEST\0",
        version: 3,
        max_header: 1 << 10,
        max_file: 1 << 20,
        name: "test file",
        contents: "values",
    };
    const KINDS: [SectionKind; 3] = [SectionKind::F32, SectionKind::U64, SectionKind::F32];

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Header {
        note: String,
        sections: [usize; 3],
    }

    fn sample() -> (Vec<f32>, Vec<u64>, Vec<f32>, Vec<u8>) {
        let a: Vec<f32> = (0..CHUNK + 5).map(|i| i as f32 * 0.25 - 7.0).collect();
        let words = vec![u64::MAX, 0, 0x0123_4567_89ab_cdef];
        let b = vec![f32::MIN_POSITIVE, -0.0, f32::INFINITY];
        let sections = [Section::F32(&a), Section::U64(&words), Section::F32(&b)];
        let header = Header {
            note: "round trip".into(),
            sections: sections.map(|s| s.count()),
        };
        let json = serde_json::to_vec(&header).unwrap();
        let mut bytes = Vec::new();
        write(&mut bytes, &TEST, &json, &sections).unwrap();
        (a, words, b, bytes)
    }

    fn error(bytes: &[u8]) -> String {
        decode(bytes, &TEST, &KINDS, |h: &Header| h.sections)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
    }

    #[test]
    fn round_trip_gives_back_every_section_bit_for_bit() {
        let (a, words, b, bytes) = sample();
        assert_eq!(&bytes[..8], TEST.magic);
        let (header, [sa, sw, sb]) = decode(&bytes, &TEST, &KINDS, |h: &Header| h.sections).unwrap();
        assert_eq!(header.note, "round trip");
        let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&sa.f32s()), bits(&a));
        assert_eq!(sw.u64s(), words);
        assert_eq!(bits(&sb.f32s()), bits(&b));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.test");
        let json = serde_json::to_vec(&header).unwrap();
        save(
            &path,
            &TEST,
            &json,
            &[Section::F32(&a), Section::U64(&words), Section::F32(&b)],
        )
        .unwrap();
        assert_eq!(read(&path, &TEST).unwrap(), bytes, "saved file holds the same bytes");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temp file left");
    }

    #[test]
    fn truncation_bit_flips_and_foreign_files_are_errors() {
        let (_, _, _, bytes) = sample();
        for cut in [
            0usize,
            7,
            8,
            15,
            19,
            20,
            100,
            bytes.len() / 2,
            bytes.len() - 4,
            bytes.len() - 1,
        ] {
            assert!(!error(&bytes[..cut]).is_empty(), "truncated to {cut} is accepted");
        }
        assert_eq!(error(&bytes[..7]), "wrong magic bytes");
        assert_eq!(error(&bytes[..19]), "truncated header");
        for pos in [16usize, 40, bytes.len() / 2, bytes.len() - 5, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[pos] ^= 0x10;
            assert_eq!(error(&bad), "checksum mismatch", "flip at {pos}");
        }
        let mut version = bytes.clone();
        version[8] = 9;
        assert_eq!(error(&version), "format version 9 is not supported");
        let mut magic = bytes.clone();
        magic[0] = b'X';
        assert_eq!(error(&magic), "wrong magic bytes");
    }

    #[test]
    fn sizes_that_do_not_fit_are_named() {
        let resealed = |header: &[u8], data: &[u8]| {
            let mut bytes = TEST.magic.to_vec();
            bytes.extend_from_slice(&TEST.version.to_le_bytes());
            bytes.extend_from_slice(&(header.len() as u32).to_le_bytes());
            bytes.extend_from_slice(header);
            bytes.extend_from_slice(data);
            let crc = crc32fast::hash(&bytes);
            bytes.extend_from_slice(&crc.to_le_bytes());
            bytes
        };
        let header = |sections: [usize; 3]| {
            serde_json::to_vec(&Header {
                note: String::new(),
                sections,
            })
            .unwrap()
        };
        assert_eq!(error(&resealed(&header([1, 1, 0]), &[0; 12])), "");
        assert_eq!(
            error(&resealed(&header([1, 1, 1]), &[0; 12])),
            "expected 16 bytes of values, found 12"
        );
        assert_eq!(
            error(&resealed(&header([1, usize::MAX / 4, 0]), &[0; 12])),
            "section sizes overflow"
        );
        assert!(error(&resealed(b"{", &[])).starts_with("header is not valid"));
        assert_eq!(
            error(&resealed(&[b' '; 2000], &[])),
            "header length 2000 does not fit the file"
        );
        let mut long = resealed(&header([0; 3]), &[]);
        long[12..16].copy_from_slice(&1000u32.to_le_bytes());
        assert_eq!(
            error(&long),
            "checksum mismatch",
            "the checksum is checked before the header length"
        );
    }

    #[test]
    fn read_refuses_files_over_the_cap_and_reports_missing_ones() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.test");
        std::fs::write(&path, vec![0u8; 2048]).unwrap();
        let small = Format { max_file: 1024, ..TEST };
        assert_eq!(
            read(&path, &small).unwrap_err().to_string(),
            "2048 bytes is larger than any test file"
        );
        match read(&dir.path().join("none.test"), &TEST) {
            Err(ContainerError::Open(e)) => assert_eq!(e.kind(), io::ErrorKind::NotFound),
            other => panic!("expected a missing file: {other:?}"),
        }
    }
}
