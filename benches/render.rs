//! Renderer speed: frames per second of the ideal render at the paper geometry
//! (430×340 px, 260 markers of 12 px), the cost of each effect on top of it, and the
//! contact + half-space step that turns a load into marker displacements.
//!
//! Run: `cargo bench --bench render` (medians in the report; target ≥ 1000 ideal
//! frames/s, i.e. ≤ 1 ms per frame).
//!
//! On a shared, loaded machine wall-clock medians include time spent waiting for a
//! core. `TACTBENCH_CPU_TIME=1 cargo bench --bench render` instead runs each case for
//! a fixed number of iterations and reports the process's CPU time per iteration
//! (user + system from `/proc/self/stat`, 10 ms ticks; ≥ 2 s of CPU per case keeps
//! the tick error below 1 %).

use std::hint::black_box;

use criterion::{criterion_group, Criterion};
use tactbench::model::HalfSpace;
use tactbench::sensor::paper_sensor;
use tactbench::sim::contact::{Contact, Indenter, LoadCase, Normal, Tangential};
use tactbench::sim::effects::{Effect, Pipeline, Scratch};
use tactbench::sim::render::{reference_markers, to_rgb16, to_rgb8, PixelFilter, Renderer};
use tactbench::sim::simulate::Simulation;

fn all_effects() -> Vec<Effect> {
    vec![
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
    ]
}

fn bench_render(c: &mut Criterion) {
    let s = paper_sensor();
    let r = Renderer::new(&s);
    let markers = reference_markers(&s);
    let mut frame = r.blank();
    c.bench_function("render/ideal_430x340_260_markers", |b| {
        b.iter(|| r.render_into(black_box(&markers), &mut frame).unwrap())
    });
    let tent = Renderer::new(&s).with_filter(PixelFilter::Tent);
    c.bench_function("render/ideal_tent_filter", |b| {
        b.iter(|| tent.render_into(black_box(&markers), &mut frame).unwrap())
    });
    c.bench_function("render/to_rgb8", |b| b.iter(|| to_rgb8(black_box(&frame))));
    c.bench_function("render/to_rgb16", |b| {
        b.iter(|| to_rgb16(black_box(&frame)))
    });

    let effects = all_effects();
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

/// 910 gf on the paper sensor's centre (Fig. 4).
fn flat_load() -> LoadCase {
    LoadCase {
        position_mm: [9.0, 6.75],
        normal: Normal::ForceN(8.924),
        tangential: Tangential::NONE,
        friction: 1.0,
    }
}

fn bench_contact(c: &mut Criterion) {
    let s = paper_sensor();
    let model = HalfSpace::from_elastomer(&s.elastomer);
    let load = flat_load();
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

/// CPU seconds (user + system) of this process, from `/proc/self/stat` (Linux).
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // Fields 14 (utime) and 15 (stime) of proc(5); `rest` starts at field 3.
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0) // USER_HZ is 100 on Linux
}

/// Runs `f` until it has used ≥ `min_cpu_s` of CPU; prints CPU time per call.
fn cpu_time(name: &str, min_cpu_s: f64, mut f: impl FnMut()) {
    let Some(t0) = process_cpu_s() else {
        eprintln!("{name}: /proc/self/stat unavailable");
        return;
    };
    let mut n = 0u64;
    let mut used = 0.0;
    while used < min_cpu_s {
        for _ in 0..50 {
            f();
        }
        n += 50;
        used = process_cpu_s().unwrap_or(t0) - t0;
    }
    let per = used / n as f64;
    println!(
        "{name:<44} {:>10.1} µs CPU/iter  ({:.0}/s, {n} iterations)",
        per * 1e6,
        1.0 / per
    );
}

fn cpu_time_report() {
    let s = paper_sensor();
    let r = Renderer::new(&s);
    let tent = Renderer::new(&s).with_filter(PixelFilter::Tent);
    let markers = reference_markers(&s);
    let mut frame = r.blank();
    cpu_time("render/ideal_430x340_260_markers", 2.0, || {
        r.render_into(black_box(&markers), &mut frame).unwrap()
    });
    cpu_time("render/ideal_tent_filter", 2.0, || {
        tent.render_into(black_box(&markers), &mut frame).unwrap()
    });
    cpu_time("render/to_rgb8", 2.0, || {
        black_box(to_rgb8(&frame));
    });
    cpu_time("render/to_rgb16", 2.0, || {
        black_box(to_rgb16(&frame));
    });
    let mut scratch = Scratch::default();
    for e in all_effects() {
        let p = Pipeline::new(vec![e.clone()], s.layers.len()).unwrap();
        let mut m = markers.clone();
        p.build_markers(&mut m);
        cpu_time(&format!("render/with_{}", e.kind()), 2.0, || {
            p.render_frame(&r, black_box(&m), 5, &mut frame, &mut scratch)
                .unwrap()
        });
    }
    let model = HalfSpace::from_elastomer(&s.elastomer);
    let load = flat_load();
    let flat = Indenter::Flat { diameter_mm: 5.0 };
    cpu_time("contact/solve_flat_5mm", 2.0, || {
        black_box(Contact::solve(&model, flat, &load).unwrap());
    });
    let mut sim = Simulation::new(s.clone(), flat, Pipeline::ideal());
    cpu_time("simulate/load_to_frame_flat_5mm_260_markers", 2.0, || {
        black_box(sim.render_load(&load, 1, &mut frame).unwrap());
    });
}

criterion_group!(benches, bench_render, bench_contact);

fn main() {
    if std::env::var_os("TACTBENCH_CPU_TIME").is_some() {
        cpu_time_report();
        return;
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}
