//! Criterion benchmark: height fog at 1920×1080, without geometry and with a
//! 10k-triangle mesh (the scenes of `tyndall bench`). Run with
//! `cargo bench -p tyndall-core --bench height_fog`; Mpixel/s = 2.0736 / time.
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use tyndall_core::bench_scenes::height_fog;

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("height_fog_1920x1080");
    g.sample_size(20);
    g.throughput(Throughput::Elements(1920 * 1080));
    for (name, mesh) in [("no_geometry", false), ("mesh_10k_triangles", true)] {
        let scene = height_fog(1920, 1080, 0, mesh).expect("the bench scene is valid");
        g.bench_function(name, |b| {
            b.iter(|| tyndall_core::render(&scene, None).map(|(img, _)| img.inscatter.len()))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
