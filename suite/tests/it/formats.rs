use std::path::Path;
use std::sync::Arc;

use arrow_array::{ArrayRef, BooleanArray, Float64Array, Int64Array, ListArray, RecordBatch, types::Float64Type};
use arrow_schema::{DataType, Field, Schema};
use dsrl_suite::catalog::{Catalog, ObservationSpace, Task};
use dsrl_suite::convert::{Converted, ImportError, SourceFormat, import_file, write_canonical};
use dsrl_suite::hdf5_file::write_dsrl_hdf5;
use dsrl_suite::parquet_file::ParquetTransitions;
use dsrl_suite::synthetic::{SyntheticSpec, transitions};
use dsrl_suite::transitions::TransitionChunk;
use parquet::arrow::ArrowWriter;
use parquet::file::reader::{FileReader, SerializedFileReader};

fn task(id: &str) -> Task {
    Catalog::embedded().unwrap().get(id).unwrap().clone()
}

fn synthetic(task: &Task, episodes: usize, seed: u64) -> Vec<TransitionChunk> {
    let mut spec = SyntheticSpec::for_task(task, episodes, seed);
    spec.chunk_rows = 700; // not a multiple of the horizon: chunks split episodes
    transitions(spec).collect()
}

fn write(task: &Task, chunks: &[TransitionChunk], out: &Path) -> Converted {
    write_canonical(
        task,
        ObservationSpace::Simulator,
        chunks.iter().cloned().map(Ok),
        vec![],
        out,
    )
    .unwrap()
}

fn read_all(path: &Path) -> TransitionChunk {
    let mut all: Option<TransitionChunk> = None;
    for chunk in ParquetTransitions::open(std::fs::File::open(path).unwrap()).unwrap() {
        let chunk = chunk.unwrap();
        match &mut all {
            None => {
                let mut c = chunk.clone();
                c.episode = None;
                c.step = None;
                all = Some(c)
            }
            Some(a) => a.append(&chunk),
        }
    }
    all.unwrap()
}

/// A fixed-size list column of float32 vectors of `dim`, row `i` null where `valid[i]` is false.
fn float_list(values: &[f32], dim: usize, valid: Option<Vec<bool>>) -> ArrayRef {
    let field = Arc::new(Field::new_list_field(DataType::Float32, false));
    Arc::new(
        arrow_array::FixedSizeListArray::try_new(
            field,
            dim as i32,
            Arc::new(arrow_array::Float32Array::from(values.to_vec())),
            valid.map(arrow_buffer::NullBuffer::from),
        )
        .unwrap(),
    )
}

fn concat(chunks: &[TransitionChunk]) -> TransitionChunk {
    let mut all = TransitionChunk::empty(chunks[0].obs_dim, chunks[0].act_dim);
    for c in chunks {
        all.append(c);
    }
    all
}

#[test]
fn canonical_parquet_round_trips_and_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let t = task("OfflineCarCircle-v0");
    let chunks = synthetic(&t, 23, 1);
    let a = write(&t, &chunks, &dir.path().join("a.parquet"));
    let b = write(&t, &chunks, &dir.path().join("b.parquet"));
    assert_eq!(a.version, b.version, "same rows must give the same bytes");
    assert_eq!(
        std::fs::read(dir.path().join("a.parquet")).unwrap().len() as u64,
        a.byte_size
    );
    let (v, _) = dsrl_suite::hashing::file_version_id(&dir.path().join("a.parquet")).unwrap();
    assert_eq!(v, a.version);
    assert_eq!(read_all(&dir.path().join("a.parquet")), concat(&chunks));
    assert_eq!(a.episode_index.len(), 23);
    assert_eq!(
        a.episode_index.iter().map(|e| e.length as usize).sum::<usize>(),
        concat(&chunks).len()
    );
    let other = write(&t, &synthetic(&t, 23, 2), &dir.path().join("c.parquet"));
    assert_ne!(other.version, a.version);
}

#[test]
fn row_groups_hold_whole_episodes_and_floats_use_byte_stream_split() {
    let dir = tempfile::tempdir().unwrap();
    // MetaDrive rows are ~2 KB, so 64 MiB row groups hold ~32 episodes: 70 episodes make several groups.
    let t = task("OfflineMetadrive-easysparse-v0");
    let chunks = synthetic(&t, 70, 3);
    let path = dir.path().join("md.parquet");
    let converted = write(&t, &chunks, &path);
    let reader = SerializedFileReader::new(std::fs::File::open(&path).unwrap()).unwrap();
    let meta = reader.metadata();
    assert!(meta.num_row_groups() >= 2, "{} row groups", meta.num_row_groups());
    let starts: Vec<u64> = converted.episode_index.iter().map(|e| e.start).collect();
    let mut row = 0u64;
    for rg in meta.row_groups() {
        assert!(
            starts.contains(&row),
            "row group starts at row {row}, inside an episode"
        );
        row += rg.num_rows() as u64;
        for col in rg.columns() {
            let path = col.column_path().string();
            let encodings: Vec<_> = col.encodings().collect();
            if path.starts_with("observations") || path == "rewards" {
                assert!(
                    encodings.contains(&parquet::basic::Encoding::BYTE_STREAM_SPLIT),
                    "{path}: {encodings:?}"
                );
            }
            assert_eq!(
                col.compression(),
                parquet::basic::Compression::ZSTD(Default::default()).codec_only()
            );
        }
    }
    let kv = meta.file_metadata().key_value_metadata().unwrap();
    assert!(
        kv.iter()
            .any(|k| k.key == "dsrl.task" && k.value.as_deref() == Some("OfflineMetadrive-easysparse-v0"))
    );
}

trait CodecOnly {
    fn codec_only(self) -> parquet::basic::Compression;
}
impl CodecOnly for parquet::basic::Compression {
    /// Column chunk metadata records the codec, not the level.
    fn codec_only(self) -> parquet::basic::Compression {
        match self {
            parquet::basic::Compression::ZSTD(_) => parquet::basic::Compression::ZSTD(Default::default()),
            other => other,
        }
    }
}

#[test]
fn hdf5_export_then_import_gives_back_the_same_version() {
    let dir = tempfile::tempdir().unwrap();
    let t = task("OfflineBallRun-v0");
    let chunks = synthetic(&t, 15, 4);
    let parquet = dir.path().join("a.parquet");
    let original = write(&t, &chunks, &parquet);
    let h5 = dir.path().join("a.hdf5");
    write_dsrl_hdf5(
        ParquetTransitions::open(std::fs::File::open(&parquet).unwrap()).unwrap(),
        &h5,
    )
    .unwrap();
    assert_eq!(SourceFormat::sniff(&h5).unwrap(), Some(SourceFormat::Hdf5));
    let (format, back) = import_file(&h5, &t, ObservationSpace::Simulator, &dir.path().join("b.parquet")).unwrap();
    assert_eq!(format, SourceFormat::Hdf5);
    assert_eq!(back.version, original.version);
    assert_eq!(back.episode_index, original.episode_index);
}

/// Writes a DSRL-layout HDF5 file the way older writers did: float64 arrays, (N, 1) columns, integer flags,
/// plus an extra key.
fn write_foreign_hdf5(all: &TransitionChunk, path: &Path, flags_as_int: bool) {
    let f = hdf5::File::create(path).unwrap();
    let n = all.len();
    let m =
        |v: &[f32], d: usize| ndarray::Array2::from_shape_vec((n, d), v.iter().map(|&x| x as f64).collect()).unwrap();
    f.new_dataset_builder()
        .deflate(4)
        .with_data(&m(&all.observations, all.obs_dim))
        .create("observations")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&m(&all.next_observations, all.obs_dim))
        .create("next_observations")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&m(&all.actions, all.act_dim))
        .create("actions")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&m(&all.rewards, 1))
        .create("rewards")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&ndarray::Array1::from(all.costs.clone()))
        .create("costs")
        .unwrap();
    for (key, flags) in [("terminals", &all.terminals), ("timeouts", &all.timeouts)] {
        if flags_as_int {
            let ints: Vec<i64> = flags.iter().map(|&b| b as i64).collect();
            f.new_dataset_builder()
                .with_data(&ndarray::Array1::from(ints))
                .create(key)
                .unwrap();
        } else {
            f.new_dataset_builder()
                .with_data(&ndarray::Array1::from(flags.clone()))
                .create(key)
                .unwrap();
        }
    }
    f.new_dataset_builder()
        .with_data(&ndarray::Array1::from(all.costs.clone()))
        .create("crash_costs")
        .unwrap();
}

#[test]
fn hdf5_with_float64_integer_flags_and_column_vectors_imports_like_the_canonical_data() {
    let dir = tempfile::tempdir().unwrap();
    let t = task("OfflineDroneRun-v0");
    let chunks = synthetic(&t, 9, 5);
    let canonical = write(&t, &chunks, &dir.path().join("a.parquet"));
    let h5 = dir.path().join("foreign.h5");
    write_foreign_hdf5(&concat(&chunks), &h5, true);
    let (_, back) = import_file(&h5, &t, ObservationSpace::Simulator, &dir.path().join("b.parquet")).unwrap();
    assert_eq!(back.version, canonical.version);
    assert_eq!(back.dropped_columns, vec!["crash_costs".to_owned()]);
}

#[test]
fn hdf5_problems_name_the_key_or_row() {
    let dir = tempfile::tempdir().unwrap();
    let t = task("OfflineDroneRun-v0");
    let all = concat(&synthetic(&t, 3, 6));
    let out = dir.path().join("out.parquet");

    let h5 = dir.path().join("missing.h5");
    let f = hdf5::File::create(&h5).unwrap();
    f.new_dataset_builder()
        .with_data(&ndarray::Array1::from(all.rewards.clone()))
        .create("rewards")
        .unwrap();
    drop(f);
    let err = import_file(&h5, &t, ObservationSpace::Simulator, &out).unwrap_err();
    assert!(matches!(err, ImportError::Malformed { .. }), "{err}");
    assert!(
        err.to_string()
            .contains("missing key(s) observations, next_observations, actions"),
        "{err}"
    );

    let h5 = dir.path().join("badflag.h5");
    write_foreign_hdf5(&all, &h5, true);
    let f = hdf5::File::open_rw(&h5).unwrap();
    f.unlink("terminals").unwrap();
    let mut ints: Vec<i64> = all.terminals.iter().map(|&b| b as i64).collect();
    ints[17] = 2;
    f.new_dataset_builder()
        .with_data(&ndarray::Array1::from(ints))
        .create("terminals")
        .unwrap();
    drop(f);
    let err = import_file(&h5, &t, ObservationSpace::Simulator, &out).unwrap_err();
    assert_eq!(
        err.to_string(),
        "row 17, column terminals: flag value 2; expected 0 or 1"
    );

    let garbage = dir.path().join("garbage.bin");
    std::fs::write(&garbage, b"not a dataset at all").unwrap();
    assert!(matches!(
        import_file(&garbage, &t, ObservationSpace::Simulator, &out),
        Err(ImportError::UnknownFormat)
    ));

    let truncated = dir.path().join("truncated.h5");
    let bytes = std::fs::read(&h5).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let err = import_file(&truncated, &t, ObservationSpace::Simulator, &out).unwrap_err();
    assert!(matches!(err, ImportError::Malformed { .. }), "{err}");
}

/// A file like `pandas.DataFrame.to_parquet` writes: float64 lists, int64 flags, no episode/step columns.
fn write_pandas_like_parquet(all: &TransitionChunk, path: &Path, extra: bool) {
    let list = |v: &[f32], d: usize| -> ArrayRef {
        Arc::new(ListArray::from_iter_primitive::<Float64Type, _, _>(
            v.chunks(d)
                .map(|row| Some(row.iter().map(|&x| Some(x as f64)).collect::<Vec<_>>())),
        ))
    };
    let f64s =
        |v: &[f32]| -> ArrayRef { Arc::new(Float64Array::from(v.iter().map(|&x| x as f64).collect::<Vec<_>>())) };
    let ints = |v: &[bool]| -> ArrayRef { Arc::new(Int64Array::from(v.iter().map(|&b| b as i64).collect::<Vec<_>>())) };
    let item = Arc::new(Field::new_list_field(DataType::Float64, true));
    let mut fields = vec![
        Field::new("observations", DataType::List(item.clone()), true),
        Field::new("next_observations", DataType::List(item.clone()), true),
        Field::new("actions", DataType::List(item), true),
        Field::new("rewards", DataType::Float64, true),
        Field::new("costs", DataType::Float64, true),
        Field::new("terminals", DataType::Int64, true),
        Field::new("timeouts", DataType::Int64, true),
    ];
    let mut columns = vec![
        list(&all.observations, all.obs_dim),
        list(&all.next_observations, all.obs_dim),
        list(&all.actions, all.act_dim),
        f64s(&all.rewards),
        f64s(&all.costs),
        ints(&all.terminals),
        ints(&all.timeouts),
    ];
    if extra {
        fields.push(Field::new("is_safe", DataType::Boolean, true));
        columns.push(Arc::new(BooleanArray::from(vec![true; all.len()])));
    }
    let batch = RecordBatch::try_new(Arc::new(Schema::new(fields)), columns).unwrap();
    let mut w = ArrowWriter::try_new(std::fs::File::create(path).unwrap(), batch.schema(), None).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}

#[test]
fn foreign_parquet_layouts_import_like_the_canonical_data() {
    let dir = tempfile::tempdir().unwrap();
    let t = task("OfflineAntRun-v0");
    let chunks = synthetic(&t, 6, 7);
    let canonical = write(&t, &chunks, &dir.path().join("a.parquet"));
    let pandas = dir.path().join("pandas.parquet");
    write_pandas_like_parquet(&concat(&chunks), &pandas, true);
    let (format, back) = import_file(&pandas, &t, ObservationSpace::Simulator, &dir.path().join("b.parquet")).unwrap();
    assert_eq!(format, SourceFormat::Parquet);
    assert_eq!(back.version, canonical.version);
    assert_eq!(back.dropped_columns, vec!["is_safe".to_owned()]);
    // The canonical file itself imports to itself.
    let (_, again) = import_file(
        &dir.path().join("a.parquet"),
        &t,
        ObservationSpace::Simulator,
        &dir.path().join("c.parquet"),
    )
    .unwrap();
    assert_eq!(again.version, canonical.version);
}

#[test]
fn wrong_task_dimensions_and_paper_space_metadrive() {
    let dir = tempfile::tempdir().unwrap();
    let ant = task("OfflineAntRun-v0");
    let src = dir.path().join("ant.parquet");
    write(&ant, &synthetic(&ant, 2, 8), &src);
    let out = dir.path().join("out.parquet");
    let err = import_file(&src, &task("OfflineBallRun-v0"), ObservationSpace::Simulator, &out).unwrap_err();
    assert_eq!(
        err.to_string(),
        "column observations: 33 features per observation, but OfflineBallRun-v0 expects 7"
    );

    // A paper-era MetaDrive file: 261 features.
    let md = task("OfflineMetadrive-hardmean-v0");
    let mut spec = SyntheticSpec::for_task(&md, 2, 9);
    spec.obs_dim = 261;
    let paper: Vec<_> = transitions(spec).collect();
    let src = dir.path().join("paper.parquet");
    write_canonical(&md, ObservationSpace::Paper, paper.into_iter().map(Ok), vec![], &src).unwrap();
    let err = import_file(&src, &md, ObservationSpace::Simulator, &out).unwrap_err();
    assert!(err.to_string().contains("261 features per observation, but OfflineMetadrive-hardmean-v0 expects 259; that is the paper's observation space"), "{err}");
    import_file(&src, &md, ObservationSpace::Paper, &out).unwrap();
    let err = import_file(&dir.path().join("ant.parquet"), &ant, ObservationSpace::Paper, &out).unwrap_err();
    assert!(err.to_string().contains("the same (33 features)"), "{err}");
}

/// A starter too large for one committed file is committed in parts of whole episodes: each part is a valid
/// dataset on its own, and the parts joined in order ingest to the canonical file of the whole, hence its version.
#[test]
fn a_dataset_split_into_parts_joins_back_to_the_same_version() {
    use dsrl_suite::convert::{join_compact_parts, parse_part_file_name, part_file_name, split_compact};
    let t = task("OfflineMetadrive-hardmean-v0");
    let dir = tempfile::tempdir().unwrap();
    let canonical = dir.path().join("canonical.parquet");
    let converted = write(&t, &synthetic(&t, 13, 22), &canonical);
    let whole = read_all(&canonical);

    let name = "SafeMetaDrive-hardmean-85-13.parquet";
    let parts: Vec<_> = (1..=3).map(|i| dir.path().join(part_file_name(name, i, 3))).collect();
    assert_eq!(
        parts[1].file_name().unwrap().to_str().unwrap(),
        "SafeMetaDrive-hardmean-85-13.part-2-of-3.parquet"
    );
    assert_eq!(
        parse_part_file_name("SafeMetaDrive-hardmean-85-13.part-2-of-3.parquet"),
        Some((name.to_owned(), 2, 3))
    );
    assert_eq!(parse_part_file_name(name), None);
    assert_eq!(parse_part_file_name("x.part-4-of-3.parquet"), None);

    let sizes = split_compact(
        &t,
        ObservationSpace::Simulator,
        &canonical,
        &converted.episode_index,
        &parts,
    )
    .unwrap();
    let mut episodes = 0;
    let mut rows = Vec::new();
    for (part, size) in parts.iter().zip(&sizes) {
        assert_eq!(*size, std::fs::metadata(part).unwrap().len());
        // Each part on its own: whole episodes, numbered from 0, about a third of the rows.
        let (_, alone) = import_file(part, &t, ObservationSpace::Simulator, &dir.path().join("alone")).unwrap();
        assert!(alone.episode_index.len() >= 3, "{}", alone.episode_index.len());
        assert_eq!(alone.episode_index[0].start, 0);
        episodes += alone.episode_index.len();
        rows.push(alone.episode_index.iter().map(|e| e.length as usize).sum::<usize>());
    }
    assert_eq!(episodes, 13);
    assert_eq!(rows.iter().sum::<usize>(), whole.len());
    assert!(
        rows.iter().all(|&r| r * 3 > whole.len() / 2),
        "balanced by rows: {rows:?}"
    );

    let joined = dir.path().join("joined.parquet");
    join_compact_parts(&t, ObservationSpace::Simulator, &parts, &joined).unwrap();
    let (_, again) = import_file(&joined, &t, ObservationSpace::Simulator, &dir.path().join("again")).unwrap();
    assert_eq!(again.version, converted.version);
    assert_eq!(read_all(&joined).observations, whole.observations);

    // Out of order, the parts are another dataset; more parts than episodes is refused.
    let swapped = [parts[1].clone(), parts[0].clone(), parts[2].clone()];
    join_compact_parts(&t, ObservationSpace::Simulator, &swapped, &joined).unwrap();
    let (_, other) = import_file(&joined, &t, ObservationSpace::Simulator, &dir.path().join("other")).unwrap();
    assert_ne!(other.version, converted.version);
    let many: Vec<_> = (1..=14).map(|i| dir.path().join(format!("p{i}.parquet"))).collect();
    let err = split_compact(
        &t,
        ObservationSpace::Simulator,
        &canonical,
        &converted.episode_index,
        &many,
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("13 episodes cannot be split into 14 parts"),
        "{err}"
    );
}

/// The compact form of a committed starter leaves out every next observation that the next row of its episode
/// starts from, and ingesting it gives back the canonical file: the same rows and the same version id. MetaDrive's
/// 259 features make the reader's batches end inside episodes, so a left-out row at a batch's end is filled from
/// the next batch.
#[test]
fn the_compact_form_is_about_half_the_size_and_ingests_to_the_same_version() {
    let t = task("OfflineMetadrive-hardmean-v0");
    let mut all = concat(&synthetic(&t, 12, 21));
    // Collected data: each step starts where the last one ended, within an episode.
    let d = all.obs_dim;
    for i in 0..all.len() - 1 {
        if !all.is_done(i) {
            let next = all.observations[(i + 1) * d..(i + 2) * d].to_vec();
            all.next_observations[i * d..(i + 1) * d].copy_from_slice(&next);
        }
    }
    assert!(all.len() > 8000, "spans more than one read batch: {}", all.len());
    let dir = tempfile::tempdir().unwrap();
    let canonical = dir.path().join("canonical.parquet");
    let converted = write(&t, std::slice::from_ref(&all), &canonical);
    let compact = dir.path().join("compact.parquet");
    // A starter in one file is the one-part split.
    let sizes = dsrl_suite::convert::split_compact(
        &t,
        ObservationSpace::Simulator,
        &canonical,
        &converted.episode_index,
        std::slice::from_ref(&compact),
    )
    .unwrap();
    let size = sizes[0];
    assert_eq!(size, std::fs::metadata(&compact).unwrap().len());
    // Observations one column per feature (episode, step, d features, next observations, actions, 4 scalars).
    let leaves = SerializedFileReader::new(std::fs::File::open(&compact).unwrap())
        .unwrap()
        .metadata()
        .file_metadata()
        .schema_descr()
        .num_columns();
    assert_eq!(leaves, d + 8);
    let canonical_size = std::fs::metadata(&canonical).unwrap().len();
    assert!(
        size * 10 < canonical_size * 6,
        "compact {size} vs canonical {canonical_size}"
    );
    // Read back: every row as it was.
    let back = read_all(&compact);
    assert_eq!(back.next_observations, all.next_observations);
    assert_eq!(back.observations, all.observations);
    // Ingested: the canonical bytes.
    let (format, reingested) =
        import_file(&compact, &t, ObservationSpace::Simulator, &dir.path().join("again")).unwrap();
    assert_eq!(format, SourceFormat::Parquet);
    assert_eq!(reingested.version, converted.version);
    assert_eq!(
        std::fs::read(dir.path().join("again")).unwrap(),
        std::fs::read(&canonical).unwrap()
    );

    // A next observation left out at an episode's last step cannot come from the next row: refused with the row.
    let small = concat(&synthetic(&task("OfflineBallRun-v0"), 2, 3));
    let last = (0..small.len()).find(|&i| small.is_done(i)).unwrap();
    let item = |nullable| {
        DataType::FixedSizeList(
            Arc::new(Field::new_list_field(DataType::Float32, false)),
            if nullable { 7 } else { 2 },
        )
    };
    let schema = Arc::new(Schema::new(vec![
        Field::new("observations", item(true), false),
        Field::new("next_observations", item(true), true),
        Field::new("actions", item(false), false),
        Field::new("rewards", DataType::Float32, false),
        Field::new("costs", DataType::Float32, false),
        Field::new("terminals", DataType::Boolean, false),
        Field::new("timeouts", DataType::Boolean, false),
    ]));
    let valid: Vec<bool> = (0..small.len()).map(|i| i != last).collect();
    let batch = RecordBatch::try_new(
        schema.clone(),
        vec![
            float_list(&small.observations, 7, None),
            float_list(&small.next_observations, 7, Some(valid)),
            float_list(&small.actions, 2, None),
            Arc::new(arrow_array::Float32Array::from(small.rewards.clone())),
            Arc::new(arrow_array::Float32Array::from(small.costs.clone())),
            Arc::new(BooleanArray::from(small.terminals.clone())),
            Arc::new(BooleanArray::from(small.timeouts.clone())),
        ],
    )
    .unwrap();
    let bad = dir.path().join("bad.parquet");
    let mut writer = ArrowWriter::try_new(std::fs::File::create(&bad).unwrap(), schema, None).unwrap();
    writer.write(&batch).unwrap();
    writer.close().unwrap();
    let err = import_file(
        &bad,
        &task("OfflineBallRun-v0"),
        ObservationSpace::Simulator,
        &dir.path().join("x"),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("null at an episode's last step"), "{err}");
    assert!(err.contains(&format!("row {last}")), "{err}");
}

/// The struct compact form's observations (one field per feature) get the list form's checks: a null feature
/// value is refused with its row, and a feature that is not a float is refused by name and type.
#[test]
fn struct_observations_with_a_null_or_a_non_float_feature_are_refused() {
    let t = task("OfflineBallRun-v0");
    let small = concat(&synthetic(&t, 2, 5));
    let (d, n) = (small.obs_dim, small.len());
    let write_with = |features: Vec<ArrayRef>, path: &Path| {
        let fields: Vec<Field> = features
            .iter()
            .enumerate()
            .map(|(j, f)| Field::new(j.to_string(), f.data_type().clone(), true))
            .collect();
        let observations = arrow_array::StructArray::try_new(fields.clone().into(), features, None).unwrap();
        let item = |dim| DataType::FixedSizeList(Arc::new(Field::new_list_field(DataType::Float32, false)), dim);
        let schema = Arc::new(Schema::new(vec![
            Field::new("observations", DataType::Struct(fields.into()), false),
            Field::new("next_observations", item(d as i32), false),
            Field::new("actions", item(small.act_dim as i32), false),
            Field::new("rewards", DataType::Float32, false),
            Field::new("costs", DataType::Float32, false),
            Field::new("terminals", DataType::Boolean, false),
            Field::new("timeouts", DataType::Boolean, false),
        ]));
        let batch = RecordBatch::try_new(
            schema.clone(),
            vec![
                Arc::new(observations) as ArrayRef,
                float_list(&small.next_observations, d, None),
                float_list(&small.actions, small.act_dim, None),
                Arc::new(arrow_array::Float32Array::from(small.rewards.clone())),
                Arc::new(arrow_array::Float32Array::from(small.costs.clone())),
                Arc::new(BooleanArray::from(small.terminals.clone())),
                Arc::new(BooleanArray::from(small.timeouts.clone())),
            ],
        )
        .unwrap();
        let mut writer = ArrowWriter::try_new(std::fs::File::create(path).unwrap(), schema, None).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
    };
    let feature = |j: usize, null_at: Option<usize>| -> ArrayRef {
        Arc::new(arrow_array::Float32Array::from(
            (0..n)
                .map(|i| (Some(i) != null_at).then_some(small.observations[i * d + j]))
                .collect::<Vec<_>>(),
        ))
    };
    let dir = tempfile::tempdir().unwrap();
    let import = |path: &Path| match import_file(path, &t, ObservationSpace::Simulator, &dir.path().join("out")) {
        Ok(_) => panic!("{} was accepted", path.display()),
        Err(e) => e.to_string(),
    };

    // As written, the struct form reads back every observation.
    let good = dir.path().join("good.parquet");
    write_with((0..d).map(|j| feature(j, None)).collect(), &good);
    assert_eq!(read_all(&good).observations, small.observations);

    let null_row = n / 2;
    let with_null = dir.path().join("null.parquet");
    write_with(
        (0..d).map(|j| feature(j, (j == 3).then_some(null_row))).collect(),
        &with_null,
    );
    let err = import(&with_null);
    assert!(err.contains("null value"), "{err}");
    assert!(err.contains(&format!("row {null_row}")), "{err}");
    assert!(err.contains("observations"), "{err}");

    let not_float = dir.path().join("int.parquet");
    let mut features: Vec<ArrayRef> = (0..d).map(|j| feature(j, None)).collect();
    features[2] = Arc::new(arrow_array::Int32Array::from(vec![1; n]));
    write_with(features, &not_float);
    let err = import(&not_float);
    assert!(err.contains("observations") && err.contains("Int32"), "{err}");
    assert!(err.contains("expected float32 or float64"), "{err}");
}
