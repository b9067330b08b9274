//! Renderer speed: frames per second of the ideal render at the paper geometry
//! (430×340 px, 260 markers of 12 px), the cost of each effect on top of it, and the
//! contact + half-space step that turns a load into marker displacements.
//!
//! Run: `cargo bench --bench render` (medians in the report; target ≥ 1000 ideal
//! frames/s, i.e. ≤ 1 ms per frame).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use tactbench::model::HalfSpace;
use tactbench::sensor::paper_sensor;
use tactbench::sim::contact::{Contact, Indenter, LoadCase, Normal, Tangential};
use tactbench::sim::effects::{Effect, Pipeline, Scratch};
use tactbench::sim::render::{reference_markers, to_rgb16, to_rgb8, Renderer};
use tactbench::sim::simulate::Simulation;

fn bench_render(c: &mut Criterion) {
    let s = paper_sensor();
    let r = Renderer::new(&s);
    let markers = reference_markers(&s);
    let mut frame = r.blank();
    c.bench_function("render/ideal_430x340_260_markers", |b| {
        b.iter(|| r.render_into(black_box(&markers), &mut frame).unwrap())
    });
    c.bench_function("render/to_rgb8", |b| b.iter(|| to_rgb8(black_box(&frame))));
    c.bench_function("render/to_rgb16", |b| {
        b.iter(|| to_rgb16(black_box(&frame)))
    });

    let effects = [
        Effect::PixelNoise {
            sigma_8bit: 2.0,
            seed: 1,
        },
        Effect::ShotNoise {
            full_scale_photons: 10_000.0,
            seed: 1,
        },
        Effect::Quantize8,
        Effect::Blur {
            sigma_px: vec![1.0, 1.5],
        },
        Effect::Illumination {
            gradient: [0.2, 0.1],
        },
        Effect::Vignetting {
            strength: 0.3,
            center_px: None,
        },
        Effect::SizeJitter {
            sigma_mm: 0.02,
            seed: 1,
        },
        Effect::PlacementJitter {
            sigma_mm: 0.02,
            seed: 1,
        },
        Effect::Shift {
            shift_px: [3.0, 0.0],
        },
        Effect::Drift {
            px_per_frame: [0.1, 0.0],
            random_walk_px: 0.05,
            seed: 1,
        },
    ];
    let mut scratch = Scratch::default();
    for e in effects {
        let p = Pipeline::new(vec![e.clone()], s.layers.len()).unwrap();
        let mut m = markers.clone();
        p.build_markers(&mut m);
        let name = format!("render/with_{}", e.kind());
        c.bench_function(&name, |b| {
            b.iter(|| {
                p.render_frame(&r, black_box(&m), 5, &mut frame, &mut scratch)
                    .unwrap()
            })
        });
    }
}

fn bench_contact(c: &mut Criterion) {
    let s = paper_sensor();
    let model = HalfSpace::from_elastomer(&s.elastomer);
    let load = LoadCase {
        position_mm: [9.0, 6.75],
        normal: Normal::ForceN(8.924),
        tangential: Tangential::NONE,
        friction: 1.0,
    };
    let flat = Indenter::Flat { diameter_mm: 5.0 };
    c.bench_function("contact/solve_flat_5mm", |b| {
        b.iter(|| Contact::solve(&model, flat, black_box(&load)).unwrap())
    });
    let mut sim = Simulation::new(s.clone(), flat, Pipeline::ideal());
    let mut frame = sim.blank_frame();
    let mut g = c.benchmark_group("simulate");
    g.sample_size(20);
    g.bench_function("load_to_frame_flat_5mm_260_markers", |b| {
        b.iter(|| sim.render_load(black_box(&load), 1, &mut frame).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench_render, bench_contact);
criterion_main!(benches);
