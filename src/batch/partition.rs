//! One partition of the merged dataset: a scan's synth file copied with
//! every column and its file metadata, the id column `scan` added (and
//! declared in the Hugging Face features when the file has them).

use super::error::BatchError;
use super::hf_json::add_string_feature;
use super::merge::ID_COLUMN;
use arrow_array::{ArrayRef, RecordBatch, StringArray};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::{EnabledStatistics, WriterProperties};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::sync::Arc;

/// Rows per record batch while copying (PNG blobs: keep batches small).
const COPY_BATCH_ROWS: usize = 16;

/// Copy a synth file to `dst` with the id column added; returns its rows.
pub(super) fn copy_partition(src: &Path, dst: &Path, id: &str) -> Result<u64, BatchError> {
    let parquet_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| BatchError::Parquet { path, source }
    };
    let file = std::fs::File::open(src).map_err(BatchError::io(src, "open the synthetic views"))?;
    let builder = ParquetRecordBatchReaderBuilder::try_new(file)
        .map_err(parquet_err(src))?
        .with_batch_size(COPY_BATCH_ROWS);
    let schema = builder.schema().clone();
    if schema.field_with_name(ID_COLUMN).is_ok() {
        return Err(BatchError::Invalid {
            path: src.to_path_buf(),
            problem: format!("already has a `{ID_COLUMN}` column, which the merge adds"),
        });
    }
    // File metadata as synth wrote it (tool version, seed, model CRC, the
    // `huggingface` features), the id column declared in the features.
    let mut kv: Vec<(String, String)> = builder
        .metadata()
        .file_metadata()
        .key_value_metadata()
        .map(|kv| {
            kv.iter()
                .filter(|k| k.key != "ARROW:schema")
                .map(|k| (k.key.clone(), k.value.clone().unwrap_or_default()))
                .collect()
        })
        .unwrap_or_default();
    for (key, value) in schema.metadata() {
        if key != "ARROW:schema" && !kv.iter().any(|(k, _)| k == key) {
            kv.push((key.clone(), value.clone()));
        }
    }
    for (key, value) in kv.iter_mut() {
        if key == "huggingface" {
            if let Some(with_id) = add_string_feature(value, ID_COLUMN) {
                *value = with_id;
            }
        }
    }
    let mut fields: Vec<Arc<Field>> = schema.fields().iter().cloned().collect();
    fields.push(Arc::new(Field::new(ID_COLUMN, DataType::Utf8, false)));
    let metadata: HashMap<String, String> = kv.iter().cloned().collect();
    let out_schema = Arc::new(Schema::new_with_metadata(fields, metadata));
    let props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_dictionary_enabled(false)
        .set_statistics_enabled(EnabledStatistics::None)
        .set_column_dictionary_enabled(ID_COLUMN.into(), true)
        .set_column_statistics_enabled(ID_COLUMN.into(), EnabledStatistics::Chunk)
        .set_max_row_group_row_count(Some(64))
        .set_key_value_metadata(Some(kv.into_iter().map(|(k, v)| KeyValue::new(k, v)).collect()))
        .build();
    let reader = builder.build().map_err(parquet_err(src))?;
    let mut rows = 0u64;
    let mut failure: Option<BatchError> = None;
    let written = crate::atomic::write_with(dst, |w| {
        let mut writer = ArrowWriter::try_new(w, out_schema.clone(), Some(props)).map_err(std::io::Error::other)?;
        for batch in reader {
            let batch = match batch {
                Ok(b) => b,
                Err(e) => {
                    failure = Some(BatchError::Arrow {
                        path: src.to_path_buf(),
                        source: e,
                    });
                    return Err(std::io::Error::other("reading failed"));
                }
            };
            let n = batch.num_rows();
            let mut columns: Vec<ArrayRef> = batch.columns().to_vec();
            columns.push(Arc::new(StringArray::from(vec![id; n])));
            let with_id = RecordBatch::try_new(out_schema.clone(), columns).map_err(std::io::Error::other)?;
            writer.write(&with_id).map_err(std::io::Error::other)?;
            rows += n as u64;
        }
        writer.close().map_err(std::io::Error::other)?;
        Ok(())
    });
    if let Some(e) = failure {
        return Err(e);
    }
    written.map_err(BatchError::io(dst, "write the merged synthetic views"))?;
    Ok(rows)
}

/// Remove `scan=<id>` folders of scans no longer merged.
pub(super) fn remove_stale_partitions(root: &Path, keep: &BTreeSet<std::ffi::OsString>) -> Result<(), BatchError> {
    let Ok(read) = std::fs::read_dir(root) else {
        return Ok(());
    };
    for item in read.filter_map(Result::ok) {
        let name = item.file_name();
        if name.to_string_lossy().starts_with(&format!("{ID_COLUMN}=")) && !keep.contains(&name) {
            let path = item.path();
            std::fs::remove_dir_all(&path).map_err(BatchError::io(&path, "remove a stale partition"))?;
        }
    }
    Ok(())
}
