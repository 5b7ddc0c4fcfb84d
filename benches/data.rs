//! Benchmarks of `ic_data`: samples/s of the object-alone and room generators through the
//! prefetching iterator with 2 worker threads (the 2-core target machine), plus one sample.
//!
//! Objects are procedural and preloaded (model points cached) before timing: the numbers are
//! the steady state of a training run, where every object has been seen.

use std::sync::Arc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use ic_data::{
    Corpus, CorpusOptions, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher, RoomSampleConfig,
    RoomSampleGenerator, Split,
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

criterion_group!(benches, object_alone, room);
criterion_main!(benches);
