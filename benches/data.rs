//! Benchmarks of `ic_data`: samples/s of the object-alone and room generators through the
//! prefetching iterator with 2 worker threads (the 2-core target machine), plus one sample;
//! and one training sample of the paper's protocol beside one of the deployment protocol
//! (640×480 camera, whole sphere, image-span distance, truncation, scale augmentation,
//! occluder, sensor model) at the `cpu` preset's M = 384 / N = 288.
//!
//! Objects are procedural and preloaded (model points cached) before timing: the numbers are
//! the steady state of a training run, where every object has been seen. The protocol group
//! uses real objects instead when `INCONTEXT_REAL_OBJECTS` names the real-object folder.

use std::sync::Arc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use ic_data::{
    Corpus, CorpusOptions, FolderSplit, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher,
    RoomSampleConfig, RoomSampleGenerator, SamplingProtocol, Split,
};

fn corpus() -> Arc<Corpus> {
    let c = Corpus::procedural(16, Split::Train, 1, CorpusOptions::default()).expect("corpus");
    c.preload().expect("preload");
    Arc::new(c)
}

fn object_alone(c: &mut Criterion) {
    let g = Arc::new(
        ObjectSampleGenerator::new(corpus(), ObjectSampleConfig::default(), 7).expect("generator"),
    );
    let mut group = c.benchmark_group("data_object_alone");
    group.sample_size(10);
    let n = 64u64;
    group.throughput(Throughput::Elements(n));
    let mut start = 0u64;
    group.bench_function("prefetch_2_workers_64_samples", |b| {
        b.iter(|| {
            let g = g.clone();
            let count = Prefetcher::new(start, Some(n), 2, 4, move |i| g.sample(i))
                .filter(|s| s.is_ok())
                .count();
            start += n;
            count
        })
    });
    group.throughput(Throughput::Elements(1));
    group.bench_function("one_sample", |b| {
        let mut i = 0;
        b.iter(|| {
            i += 1;
            g.sample(i).expect("sample")
        })
    });
    group.finish();
}

fn room(c: &mut Criterion) {
    let g = Arc::new(
        RoomSampleGenerator::new(corpus(), RoomSampleConfig::default(), 7).expect("generator"),
    );
    let mut group = c.benchmark_group("data_room_640x480");
    group.sample_size(10);
    let n = 8u64;
    group.throughput(Throughput::Elements(n));
    let mut start = 0u64;
    group.bench_function("prefetch_2_workers_8_samples", |b| {
        b.iter(|| {
            let g = g.clone();
            let count = Prefetcher::new(start, Some(n), 2, 2, move |i| g.sample(i))
                .filter(|s| s.is_ok())
                .count();
            start += n;
            count
        })
    });
    group.finish();
}

/// The training corpus of the protocol benchmarks: 16 real objects when
/// `INCONTEXT_REAL_OBJECTS` points at the folder (with its `split.json`), else procedural.
fn training_corpus() -> Arc<Corpus> {
    let Some(dir) = std::env::var_os("INCONTEXT_REAL_OBJECTS") else {
        return corpus();
    };
    let dir = std::path::PathBuf::from(dir);
    let how = FolderSplit::File(dir.join("split.json"));
    let all = Corpus::mesh_folder(&dir, &how, Split::Train, CorpusOptions::default())
        .expect("real objects");
    let first: Vec<String> = all
        .entries()
        .iter()
        .take(16)
        .map(|e| e.id.clone())
        .collect();
    let tmp = std::env::temp_dir().join("ic_bench_real_split.json");
    std::fs::write(&tmp, serde_json::json!({ "train": first }).to_string()).expect("split file");
    let c = Corpus::mesh_folder(
        &dir,
        &FolderSplit::File(tmp),
        Split::Train,
        CorpusOptions::default(),
    )
    .expect("real objects");
    c.preload().expect("preload");
    Arc::new(c)
}

fn protocols(c: &mut Criterion) {
    let objects = training_corpus();
    let mut group = c.benchmark_group("data_protocol_cpu_preset");
    group.sample_size(20);
    group.throughput(Throughput::Elements(1));
    for protocol in [SamplingProtocol::Paper, SamplingProtocol::Deployment] {
        let cfg = ObjectSampleConfig {
            model_points: 384,
            observed_points: 288,
            ..protocol.config()
        };
        let g = ObjectSampleGenerator::new(objects.clone(), cfg, 7).expect("generator");
        // Many different samples per measurement: deployment samples vary a lot in size.
        let mut i = 0;
        group.bench_function(format!("one_sample_{protocol}"), |b| {
            b.iter(|| {
                i += 1;
                g.sample(i).expect("sample")
            })
        });
    }
    group.finish();
}

criterion_group!(benches, object_alone, room, protocols);
criterion_main!(benches);
