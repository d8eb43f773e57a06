//! The Parquet output of `synth` (FORMATS.md section 4): one row per view,
//! streamed one row group per batch of views, snappy-compressed, with
//! key-value metadata; written to a temp file beside the output and renamed
//! only when complete, so an interrupted run leaves nothing at the path.

use super::error::SynthError;
use super::triplet::SynthView;
use arrow_array::builder::OffsetBufferBuilder;
use arrow_array::{
    ArrayRef, BinaryArray, FixedSizeListArray, Float32Array, Float64Array, Int32Array, ListArray, RecordBatch,
    StringArray, StructArray,
};
use arrow_schema::{DataType, Field, Fields, Schema, SchemaRef};
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::{EnabledStatistics, WriterProperties};
use parquet::schema::types::ColumnPath;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Image columns: structs `{bytes, path}` as Hugging Face `datasets` stores images.
const IMAGE_COLUMNS: [&str; 3] = ["rgb", "depth", "mask"];

/// Leaf columns holding PNG blobs (no statistics or dictionaries: every value is unique).
const BLOB_COLUMNS: [[&str; 2]; 3] = [["rgb", "bytes"], ["depth", "bytes"], ["mask", "bytes"]];

/// Fields of one `boxes_2d` entry.
fn box_fields() -> Fields {
    Fields::from(vec![
        Field::new("instance_id", DataType::Int32, false),
        Field::new("label", DataType::Utf8, false),
        Field::new("x0", DataType::Float32, false),
        Field::new("y0", DataType::Float32, false),
        Field::new("x1", DataType::Float32, false),
        Field::new("y1", DataType::Float32, false),
    ])
}

/// Element field of a fixed-size list of f64.
fn f64_item() -> Arc<Field> {
    Arc::new(Field::new("item", DataType::Float64, false))
}

/// Element field of `boxes_2d`.
fn box_item() -> Arc<Field> {
    Arc::new(Field::new("item", DataType::Struct(box_fields()), false))
}

/// Fields of an image column: the PNG in `bytes`, `path` always null.
fn image_fields() -> Fields {
    Fields::from(vec![
        Field::new("bytes", DataType::Binary, true),
        Field::new("path", DataType::Utf8, true),
    ])
}

/// The `huggingface` schema metadata: the `datasets` features of every column,
/// so `Dataset.from_parquet` decodes the image columns as images.
fn huggingface_features() -> String {
    let value = |dtype: &str| serde_json::json!({"dtype": dtype, "_type": "Value"});
    let floats =
        |length: usize| serde_json::json!({"feature": value("float64"), "length": length, "_type": "Sequence"});
    let image = serde_json::json!({"_type": "Image"});
    let box_2d = serde_json::json!({
        "instance_id": value("int32"),
        "label": value("string"),
        "x0": value("float32"),
        "y0": value("float32"),
        "x1": value("float32"),
        "y1": value("float32"),
    });
    let features = serde_json::json!({
        "view_id": value("int32"),
        "width": value("int32"),
        "height": value("int32"),
        "intrinsics": floats(4),
        "camera_to_world": floats(16),
        "rgb": image,
        "depth": image,
        "mask": image,
        "boxes_2d": [box_2d],
    });
    serde_json::json!({"info": {"features": features}}).to_string()
}

/// The Arrow schema of the synth file, exactly FORMATS.md section 4.
pub fn synth_schema() -> Schema {
    // Nullable as `datasets` declares an Image, or it ignores the feature.
    let image = |name: &str| Field::new(name, DataType::Struct(image_fields()), true);
    let fields = vec![
        Field::new("view_id", DataType::Int32, false),
        Field::new("width", DataType::Int32, false),
        Field::new("height", DataType::Int32, false),
        Field::new("intrinsics", DataType::FixedSizeList(f64_item(), 4), false),
        Field::new("camera_to_world", DataType::FixedSizeList(f64_item(), 16), false),
        image(IMAGE_COLUMNS[0]),
        image(IMAGE_COLUMNS[1]),
        image(IMAGE_COLUMNS[2]),
        Field::new("boxes_2d", DataType::List(box_item()), false),
    ];
    let metadata = [("huggingface".to_string(), huggingface_features())];
    Schema::new_with_metadata(
        fields,
        metadata.into_iter().collect::<std::collections::HashMap<_, _>>(),
    )
}

/// A Parquet file being written; dropping it unfinished removes the temp file.
pub struct SynthWriter {
    writer: Option<ArrowWriter<File>>,
    schema: SchemaRef,
    tmp: PathBuf,
    out: PathBuf,
    rows: usize,
}

/// Temporary path beside `out` (same pattern as [`crate::atomic`]).
fn temp_path(out: &Path) -> PathBuf {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    out.with_file_name(format!(".{name}.tmp{}", std::process::id()))
}

impl SynthWriter {
    /// Start writing `out` (through a temp file) with key-value `metadata`.
    pub fn create(out: &Path, metadata: &[(&str, String)]) -> Result<SynthWriter, SynthError> {
        let io = |source| SynthError::Io {
            path: out.to_path_buf(),
            source,
        };
        if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let tmp = temp_path(out);
        let file = File::create(&tmp).map_err(io)?;
        let mut props = WriterProperties::builder()
            .set_compression(Compression::SNAPPY)
            .set_key_value_metadata(Some(
                metadata
                    .iter()
                    .map(|(k, v)| KeyValue::new(k.to_string(), v.clone()))
                    .collect(),
            ));
        for col in BLOB_COLUMNS {
            let path = ColumnPath::new(col.iter().map(|part| part.to_string()).collect());
            props = props
                .set_column_statistics_enabled(path.clone(), EnabledStatistics::None)
                .set_column_dictionary_enabled(path, false);
        }
        let schema = Arc::new(synth_schema());
        let mut this = SynthWriter {
            writer: None,
            schema: schema.clone(),
            tmp,
            out: out.to_path_buf(),
            rows: 0,
        };
        let writer = ArrowWriter::try_new(file, schema, Some(props.build())).map_err(|e| this.parquet_error(e))?;
        this.writer = Some(writer);
        Ok(this)
    }

    fn parquet_error(&self, source: parquet::errors::ParquetError) -> SynthError {
        SynthError::Parquet {
            path: self.out.clone(),
            source,
        }
    }

    /// Views written so far.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Write `views` as one row group; view ids continue from the rows written.
    pub fn write_group(&mut self, views: &[SynthView]) -> Result<(), SynthError> {
        if views.is_empty() {
            return Ok(());
        }
        let batch = self.batch(views)?;
        let Some(writer) = self.writer.as_mut() else {
            return Err(SynthError::Options("the Parquet writer is already finished".into()));
        };
        let result = writer.write(&batch).and_then(|()| writer.flush());
        result.map_err(|e| self.parquet_error(e))?;
        self.rows += views.len();
        Ok(())
    }

    /// Add key-value metadata written at the end of the file.
    pub fn append_metadata(&mut self, key: &str, value: String) {
        if let Some(w) = self.writer.as_mut() {
            w.append_key_value_metadata(KeyValue::new(key.to_string(), value));
        }
    }

    /// Close the file, sync it and rename it onto the output path; returns its size in bytes.
    pub fn finish(mut self) -> Result<u64, SynthError> {
        let Some(writer) = self.writer.take() else {
            return Err(SynthError::Options("the Parquet writer is already finished".into()));
        };
        let io = |source| SynthError::Io {
            path: self.out.clone(),
            source,
        };
        let result = (|| {
            let file = writer.into_inner().map_err(|e| self.parquet_error(e))?;
            file.sync_all().map_err(io)?;
            let bytes = file.metadata().map_err(io)?.len();
            std::fs::rename(&self.tmp, &self.out).map_err(io)?;
            Ok(bytes)
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result
    }

    /// One record batch of `views`.
    fn batch(&self, views: &[SynthView]) -> Result<RecordBatch, SynthError> {
        let int = |f: &dyn Fn(usize, &SynthView) -> i64| -> Result<ArrayRef, SynthError> {
            let values = views
                .iter()
                .enumerate()
                .map(|(i, v)| {
                    i32::try_from(f(i, v))
                        .map_err(|_| SynthError::Options("a value does not fit the int32 column".into()))
                })
                .collect::<Result<Vec<i32>, _>>()?;
            Ok(Arc::new(Int32Array::from(values)))
        };
        let first = self.rows;
        let view_id = int(&|i, _| (first + i) as i64)?;
        let width = int(&|_, v| i64::from(v.spec.width))?;
        let height = int(&|_, v| i64::from(v.spec.height))?;
        let intrinsics: Vec<f64> = views
            .iter()
            .flat_map(|v| {
                let k = v.spec.intrinsics;
                [k.fx, k.fy, k.cx, k.cy]
            })
            .collect();
        // The transpose's column-major storage is the row-major order.
        let poses: Vec<f64> = views
            .iter()
            .flat_map(|v| v.spec.camera_to_world.to_homogeneous().transpose().as_slice().to_vec())
            .collect();
        let fixed = |values: Vec<f64>, size: i32| -> Result<ArrayRef, SynthError> {
            let list = FixedSizeListArray::try_new(f64_item(), size, Arc::new(Float64Array::from(values)), None)
                .map_err(|e| SynthError::Options(format!("internal: cannot build a fixed-size list: {e}")))?;
            Ok(Arc::new(list))
        };
        let image = |f: fn(&SynthView) -> &[u8]| -> Result<ArrayRef, SynthError> {
            let bytes: ArrayRef = Arc::new(BinaryArray::from_iter_values(views.iter().map(f)));
            let paths: ArrayRef = Arc::new(StringArray::new_null(views.len()));
            let column = StructArray::try_new(image_fields(), vec![bytes, paths], None)
                .map_err(|e| SynthError::Options(format!("internal: cannot build an image column: {e}")))?;
            Ok(Arc::new(column))
        };
        let columns: Vec<ArrayRef> = vec![
            view_id,
            width,
            height,
            fixed(intrinsics, 4)?,
            fixed(poses, 16)?,
            image(|v| &v.rgb_png)?,
            image(|v| &v.depth_png)?,
            image(|v| &v.mask_png)?,
            boxes_column(views)?,
        ];
        RecordBatch::try_new(self.schema.clone(), columns)
            .map_err(|e| SynthError::Options(format!("internal: record batch does not match the schema: {e}")))
    }
}

/// The `boxes_2d` column: one list of box structs per view.
fn boxes_column(views: &[SynthView]) -> Result<ArrayRef, SynthError> {
    let all = || views.iter().flat_map(|v| v.boxes.iter());
    let ids = all()
        .map(|b| i32::try_from(b.instance_id))
        .collect::<Result<Vec<i32>, _>>()
        .map_err(|_| SynthError::Options("an instance id does not fit the int32 column".into()))?;
    let coord =
        |f: fn(&super::triplet::Box2d) -> f32| -> ArrayRef { Arc::new(Float32Array::from_iter_values(all().map(f))) };
    let children: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from(ids)),
        Arc::new(StringArray::from_iter_values(all().map(|b| b.label.as_str()))),
        coord(|b| b.x0),
        coord(|b| b.y0),
        coord(|b| b.x1),
        coord(|b| b.y1),
    ];
    let internal = |e: arrow_schema::ArrowError| SynthError::Options(format!("internal: cannot build boxes_2d: {e}"));
    let structs = StructArray::try_new(box_fields(), children, None).map_err(internal)?;
    let mut offsets = OffsetBufferBuilder::<i32>::new(views.len());
    for v in views {
        offsets.push_length(v.boxes.len());
    }
    let list = ListArray::try_new(box_item(), offsets.finish(), Arc::new(structs), None).map_err(internal)?;
    Ok(Arc::new(list))
}

impl Drop for SynthWriter {
    fn drop(&mut self) {
        // Unfinished (error, interruption): leave nothing behind.
        if self.writer.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::Intrinsics;
    use crate::synth::poses_file::ViewSpec;
    use crate::synth::triplet::Box2d;
    use arrow_array::cast::AsArray;
    use arrow_array::types::{Float32Type, Float64Type, Int32Type};
    use arrow_array::Array;
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;

    fn view(i: usize) -> SynthView {
        SynthView {
            spec: ViewSpec {
                camera_to_world: nalgebra::IsometryMatrix3::translation(i as f64, 2.0, 3.0),
                intrinsics: Intrinsics {
                    fx: 100.0,
                    fy: 101.0,
                    cx: 50.0 + i as f64,
                    cy: 40.0,
                },
                width: 100,
                height: 80,
            },
            rgb_png: vec![1, 2, i as u8],
            depth_png: vec![4; i + 1],
            mask_png: vec![],
            boxes: (0..i % 3)
                .map(|b| Box2d {
                    instance_id: b as u32 + 1,
                    label: format!("obj{b}"),
                    x0: 1.0,
                    y0: 2.0,
                    x1: 3.5,
                    y1: 4.0 + i as f32,
                })
                .collect(),
        }
    }

    #[test]
    fn rows_round_trip_through_the_arrow_reader_in_bounded_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("sub/views.parquet");
        let mut w = SynthWriter::create(&out, &[("seed", "7".into())]).unwrap();
        let views: Vec<SynthView> = (0..7).map(view).collect();
        w.write_group(&views[..3]).unwrap();
        w.write_group(&views[3..]).unwrap();
        w.append_metadata("views", "7".into());
        assert!(!out.exists(), "nothing at the output path before finishing");
        let bytes = w.finish().unwrap();
        assert_eq!(bytes, std::fs::metadata(&out).unwrap().len());
        assert_eq!(
            std::fs::read_dir(out.parent().unwrap()).unwrap().count(),
            1,
            "temp file left behind"
        );

        let builder = ParquetRecordBatchReaderBuilder::try_new(File::open(&out).unwrap()).unwrap();
        let meta = builder.metadata().clone();
        assert_eq!(meta.num_row_groups(), 2);
        let kv = meta.file_metadata().key_value_metadata().unwrap();
        let get = |k: &str| kv.iter().find(|e| e.key == k).and_then(|e| e.value.clone());
        assert_eq!(get("seed").as_deref(), Some("7"));
        assert_eq!(get("views").as_deref(), Some("7"));
        assert_eq!(builder.schema().fields(), synth_schema().fields());
        let batches: Vec<RecordBatch> = builder.build().unwrap().map(|b| b.unwrap()).collect();
        let batch = arrow_select_concat(&batches);
        assert_eq!(batch.len(), 7);
        for (i, v) in views.iter().enumerate() {
            assert_eq!(batch.view_id[i], i as i32);
            assert_eq!(batch.width[i], 100);
            assert_eq!(batch.k[i], vec![100.0, 101.0, 50.0 + i as f64, 40.0]);
            let t = &batch.pose[i];
            assert_eq!(
                (t[3], t[7], t[11], t[15]),
                (i as f64, 2.0, 3.0, 1.0),
                "row-major translation column"
            );
            assert_eq!(batch.rgb[i], v.rgb_png);
            assert_eq!(batch.depth[i], v.depth_png);
            assert_eq!(
                batch.boxes[i],
                v.boxes
                    .iter()
                    .map(|b| (b.instance_id as i32, b.label.clone(), [b.x0, b.y0, b.x1, b.y1]))
                    .collect::<Vec<_>>()
            );
        }
    }

    /// Columns of all batches, flattened to plain vectors.
    #[derive(Default)]
    struct Rows {
        view_id: Vec<i32>,
        width: Vec<i32>,
        k: Vec<Vec<f64>>,
        pose: Vec<Vec<f64>>,
        rgb: Vec<Vec<u8>>,
        depth: Vec<Vec<u8>>,
        boxes: Vec<Vec<(i32, String, [f32; 4])>>,
    }

    impl Rows {
        fn len(&self) -> usize {
            self.view_id.len()
        }
    }

    fn arrow_select_concat(batches: &[RecordBatch]) -> Rows {
        let mut rows = Rows::default();
        for b in batches {
            let col = |name: &str| b.column_by_name(name).unwrap().clone();
            rows.view_id
                .extend(col("view_id").as_primitive::<Int32Type>().values().iter());
            rows.width
                .extend(col("width").as_primitive::<Int32Type>().values().iter());
            for (name, out) in [("intrinsics", &mut rows.k), ("camera_to_world", &mut rows.pose)] {
                let list = col(name);
                let list = list.as_fixed_size_list();
                for i in 0..list.len() {
                    out.push(list.value(i).as_primitive::<Float64Type>().values().to_vec());
                }
            }
            for (name, out) in [("rgb", &mut rows.rgb), ("depth", &mut rows.depth)] {
                let c = col(name);
                let image = c.as_struct();
                assert_eq!(image.column(1).null_count(), image.len(), "path is null");
                out.extend(image.column(0).as_binary::<i32>().iter().map(|v| v.unwrap().to_vec()));
            }
            let boxes = col("boxes_2d");
            let boxes = boxes.as_list::<i32>();
            for i in 0..boxes.len() {
                let s = boxes.value(i);
                let s = s.as_struct();
                let f = |n: usize| s.column(n).as_primitive::<Float32Type>().values().to_vec();
                let (x0, y0, x1, y1) = (f(2), f(3), f(4), f(5));
                let ids = s.column(0).as_primitive::<Int32Type>().values().to_vec();
                let labels = s.column(1).as_string::<i32>();
                rows.boxes.push(
                    (0..s.len())
                        .map(|j| (ids[j], labels.value(j).to_string(), [x0[j], y0[j], x1[j], y1[j]]))
                        .collect(),
                );
            }
        }
        rows
    }

    #[test]
    fn dropping_an_unfinished_writer_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("views.parquet");
        let mut w = SynthWriter::create(&out, &[]).unwrap();
        w.write_group(&[view(1)]).unwrap();
        drop(w);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
