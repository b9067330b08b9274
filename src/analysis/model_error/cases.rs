//! The data of the model-error study: the sensor at each thickness, the camera
//! effect sets of a base scene, and each (thickness, physics, effect set, load) data
//! set, by the forward model or rendered, tracked and measured (see [`super`]).

use super::*;

/// The camera effects available to the effect axis: the `[[effects]]` tables (and the
/// `pixel_filter`) of a base scene file, in the file's order.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraEffects {
    /// The file they came from (for messages; `(default camera)` for the built-in).
    pub source: PathBuf,
    /// `pixel_filter`, when the file sets it.
    pub pixel_filter: Option<String>,
    /// The effect tables, each with its `kind`.
    pub tables: Vec<toml::Table>,
}

impl CameraEffects {
    /// The built-in default ([`DEFAULT_CAMERA_SCENE`]).
    pub fn default_camera() -> Self {
        // A constant of this module, covered by a test.
        Self::from_scene_text(DEFAULT_CAMERA_SCENE, Path::new("(default camera)")).unwrap_or_else(
            |_| CameraEffects {
                source: PathBuf::from("(default camera)"),
                pixel_filter: None,
                tables: Vec::new(),
            },
        )
    }

    /// The effects of scene TOML text (`path` for messages). Only `[[effects]]` and
    /// `pixel_filter` are read; every other key (sensor, indenter, load, …) is replaced
    /// by the study's. Each table must have a string `kind`; its other keys are checked
    /// by the scene parser when the study builds its scenes ([`Self::validate`]).
    pub fn from_scene_text(text: &str, path: &Path) -> Result<Self, ModelErrorStudyError> {
        let err = |message: String| ModelErrorStudyError::Effects {
            path: path.to_path_buf(),
            message,
        };
        let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
            err(format!("not valid TOML: {}", e.to_string().trim_end()))
        })?;
        let pixel_filter = match table.get("pixel_filter") {
            None => None,
            Some(toml::Value::String(s)) => Some(s.clone()),
            Some(v) => return Err(err(format!("pixel_filter = {v} must be a string"))),
        };
        let mut tables = Vec::new();
        match table.get("effects") {
            None => {}
            Some(toml::Value::Array(a)) => {
                for (i, v) in a.iter().enumerate() {
                    let Some(t) = v.as_table() else {
                        return Err(err(format!("effects[{i}] must be a table ([[effects]])")));
                    };
                    match t.get("kind") {
                        Some(toml::Value::String(_)) => tables.push(t.clone()),
                        _ => {
                            return Err(err(format!(
                                "effects[{i}] needs kind = \"<effect kind>\" (a string)"
                            )))
                        }
                    }
                }
            }
            Some(_) => {
                return Err(err(
                    "effects must be an array of tables ([[effects]])".into()
                ))
            }
        }
        Ok(CameraEffects {
            source: path.to_path_buf(),
            pixel_filter,
            tables,
        })
    }

    /// Reads a base scene file.
    pub fn from_path(path: &Path) -> Result<Self, ModelErrorStudyError> {
        let text = std::fs::read_to_string(path).map_err(|e| ModelErrorStudyError::Effects {
            path: path.to_path_buf(),
            message: format!("cannot read: {e}"),
        })?;
        Self::from_scene_text(&text, path)
    }

    /// The effect kinds available, in file order (a kind may appear more than once).
    pub fn kinds(&self) -> Vec<String> {
        self.tables
            .iter()
            .filter_map(|t| t.get("kind").and_then(|k| k.as_str()).map(String::from))
            .collect()
    }

    /// The tables of the listed kinds, in the file's order; an error names a kind the
    /// file does not have.
    pub fn select(&self, kinds: &[String]) -> Result<Vec<toml::Table>, ModelErrorStudyError> {
        let have = self.kinds();
        if let Some(k) = kinds.iter().find(|k| !have.contains(k)) {
            return Err(ModelErrorStudyError::Effects {
                path: self.source.clone(),
                message: format!(
                    "effect `{k}` is not among the scene's [[effects]] (it has: {}); add a \
                     [[effects]] table with kind = \"{k}\" and its parameters (see the scene.toml \
                     docs) and pass the file with --scene",
                    if have.is_empty() {
                        "none".to_string()
                    } else {
                        have.join(", ")
                    }
                ),
            });
        }
        Ok(self
            .tables
            .iter()
            .filter(|t| {
                t.get("kind")
                    .and_then(|k| k.as_str())
                    .is_some_and(|k| kinds.iter().any(|x| x == k))
            })
            .cloned()
            .collect())
    }

    /// Checks every effect table through the scene parser on `sensor` (errors name the
    /// base file and the effect's index in it), and that every kind of `sets` exists.
    pub fn validate(
        &self,
        sensor: &Sensor,
        sets: &[EffectSet],
    ) -> Result<(), ModelErrorStudyError> {
        for s in sets {
            if let EffectSet::Pipeline(k) = s {
                self.select(k)?;
            }
        }
        if sets.iter().any(|s| matches!(s, EffectSet::Pipeline(_))) {
            pipeline_scene(
                self,
                &self.tables,
                sensor.clone(),
                ModelKind::HalfSpace,
                LoadKind::Normal,
            )?;
        }
        Ok(())
    }
}

/// Where the pipeline's probe is centred: the centre of the Fig. 6 patch (nodes
/// `ix ∈ 3..=6, iy ∈ 2..=5`), mm.
pub(super) fn patch_centre_mm(sensor: &Sensor) -> [f64; 2] {
    let g = &sensor.force_grid;
    [
        g.origin_mm[0] + 4.5 * g.pitch_mm,
        g.origin_mm[1] + 3.5 * g.pitch_mm,
    ]
}

/// The scene of a pipeline data set (see the module docs): `effects` through the
/// scene's own parser, errors naming the base scene file.
fn pipeline_scene(
    camera: &CameraEffects,
    effects: &[toml::Table],
    sensor: Sensor,
    physics: ModelKind,
    load: LoadKind,
) -> Result<Scene, ModelErrorStudyError> {
    use toml::Value;
    let c = patch_centre_mm(&sensor);
    let mut t = toml::Table::new();
    t.insert("sensor".into(), Value::String("(model-error study)".into()));
    if let Some(p) = &camera.pixel_filter {
        t.insert("pixel_filter".into(), Value::String(p.clone()));
    }
    let mut ind = toml::Table::new();
    ind.insert("kind".into(), Value::String("flat".into()));
    ind.insert("diameter_mm".into(), Value::Float(PROBE_DIAMETER_MM));
    t.insert("indenter".into(), Value::Table(ind));
    let mut l = toml::Table::new();
    l.insert(
        "position_mm".into(),
        Value::Array(vec![Value::Float(c[0]), Value::Float(c[1])]),
    );
    l.insert("normal_force_gf".into(), Value::Float(100.0));
    if load == LoadKind::Mixed {
        l.insert("tangential_force_gf".into(), Value::Float(50.0));
        l.insert("direction_deg".into(), Value::Float(90.0));
    }
    t.insert("load".into(), Value::Table(l));
    let mut p = toml::Table::new();
    p.insert("model".into(), Value::String(physics.name().into()));
    t.insert("physics".into(), Value::Table(p));
    t.insert(
        "effects".into(),
        Value::Array(effects.iter().cloned().map(Value::Table).collect()),
    );
    let text = toml::to_string(&t).map_err(|e| ModelErrorStudyError::Effects {
        path: camera.source.clone(),
        message: format!("cannot write the study's scene: {e}"),
    })?;
    Ok(Scene::from_toml_str(&text, &camera.source, sensor)?)
}

/// `base` at thickness `h` (mm) with its marker depths scaled, when needed, so that the
/// deepest lies at `max_depth_fraction · h` (see the module docs). The solver model is
/// left as in `base`.
pub fn sensor_at_thickness(
    base: &Sensor,
    h: f64,
    max_depth_fraction: f64,
) -> Result<Sensor, ModelErrorStudyError> {
    if !(h.is_finite() && h > 0.0) {
        return Err(ModelErrorStudyError::InvalidOption(format!(
            "thickness {h} mm must be a finite number > 0"
        )));
    }
    if !(max_depth_fraction.is_finite() && max_depth_fraction > 0.0 && max_depth_fraction <= 1.0) {
        return Err(ModelErrorStudyError::InvalidOption(format!(
            "max depth fraction {max_depth_fraction} must be in (0, 1]"
        )));
    }
    let deepest = base
        .layers
        .iter()
        .map(|l| l.depth_mm)
        .fold(0.0f64, f64::max);
    if deepest.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Err(ModelErrorStudyError::Sensor(
            "the sensor has no marker layer below the surface".into(),
        ));
    }
    let mut s = base.clone();
    s.elastomer.thickness_mm = h;
    let scale = (max_depth_fraction * h / deepest).min(1.0);
    for l in &mut s.layers {
        l.depth_mm *= scale;
    }
    Ok(s)
}

/// The data of one (thickness, physics, effect set, load).
pub(super) struct Data {
    /// Per realisation, displacements of the used markers, mm.
    pub(super) frames: Vec<Vec<f64>>,
    /// Indices of the used markers into the sensor's full marker list.
    pub(super) used: Vec<usize>,
    pub(super) truth: Vec<f64>,
    pub(super) applied: [f64; 3],
    pub(super) track_s: Option<f64>,
}

/// The data of one (thickness, physics, effect set, load); `Err` is why it cannot be
/// made (reported in the rows).
pub(super) fn make_data(
    sensor: &Sensor,
    sites: &[MarkerSite],
    camera: &CameraEffects,
    set: &EffectSet,
    physics: ModelKind,
    load: LoadKind,
    options: &ModelErrorOptions,
) -> Result<Data, String> {
    match set {
        EffectSet::Forward => {
            let truth = load.node_forces(sensor).map_err(|e| e.to_string())?;
            let mut applied = [0.0; 3];
            for (i, v) in truth.iter().enumerate() {
                applied[i % 3] += v;
            }
            let m = ForwardModel::of_kind(physics, &sensor.elastomer);
            let mut u = model::forward(&m, sites, &sensor.force_points_mm(), &truth)
                .map_err(|e| e.to_string())?;
            if options.noise_px > 0.0 {
                // One draw per data set, from a stream of its own.
                let stream = (sensor.elastomer.thickness_mm.to_bits())
                    ^ ((physics as u64) << 2)
                    ^ (load as u64);
                let mut rng = Rng::stream(options.seed, stream);
                let s = options.noise_px * sensor.camera.mm_per_px;
                u.iter_mut().for_each(|v| *v += s * rng.normal());
            }
            Ok(Data {
                frames: vec![u],
                used: (0..sites.len()).collect(),
                truth,
                applied,
                track_s: None,
            })
        }
        EffectSet::Pipeline(kinds) => {
            if load == LoadKind::Tangential {
                return Err(
                    "a contact cannot carry a tangential load without a normal one \
                            (Coulomb friction: |Q| <= mu P), so the pipeline has no purely \
                            tangential load; see the forward (effects none) rows"
                        .into(),
                );
            }
            let effects = camera.select(kinds).map_err(|e| e.to_string())?;
            let scene = pipeline_scene(camera, &effects, sensor.clone(), physics, load)
                .map_err(|e| e.to_string())?;
            pipeline_data(&scene, sites, options)
        }
    }
}

/// Renders, detects and tracks a pipeline data set.
fn pipeline_data(
    scene: &Scene,
    sites: &[MarkerSite],
    options: &ModelErrorOptions,
) -> Result<Data, String> {
    let sensor = &scene.sensor;
    crate::sim::scene::check_physics(scene.physics, sensor).map_err(|e| e.to_string())?;
    let mut sim = Simulation::from_scene(scene);
    let eight_bit = sim.pipeline().quantizes_to_8bit();
    let convert = |img: &image::Rgb32FImage| {
        if eight_bit {
            Frame::Rgb8(to_rgb8(img))
        } else {
            Frame::Rgb16(to_rgb16(img))
        }
    };
    let mut buf = sim.blank_frame();
    sim.render_reference(&mut buf).map_err(|e| e.to_string())?;
    let reference = convert(&buf);
    let mut frames = Vec::with_capacity(options.realisations);
    let mut contact = None;
    for k in 1..=options.realisations {
        let t = sim
            .render_load(&scene.load, k as u64, &mut buf)
            .map_err(|e| e.to_string())?;
        frames.push(convert(&buf));
        if contact.is_none() {
            contact = t.contact;
        }
    }
    let contact = contact.ok_or("the scene rendered no contact")?;
    let reference = detect(&reference.view(), sensor, &DetectConfig::default())
        .map_err(|e| format!("reference detection: {e}"))?;
    // Index of each layer's first marker in the full marker list.
    let mut offsets = Vec::with_capacity(sensor.layers.len());
    let mut n = 0;
    for l in &sensor.layers {
        offsets.push(n);
        n += l.markers.map_or(0, |m| m.grid.len());
    }
    let mut tracker = Tracker::new(
        reference,
        TrackConfig {
            mode: TrackMode::PerWindow,
            ..TrackConfig::default()
        },
    );
    let n_ref = tracker.reference().markers.len();
    let mut ok = vec![true; n_ref];
    for f in &frames {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        for (o, t) in ok.iter_mut().zip(tracks) {
            *o &= t.status == MarkerStatus::Ok;
        }
    }
    let tracked: Vec<usize> = (0..n_ref).filter(|&i| ok[i]).collect();
    let used: Vec<usize> = tracked
        .iter()
        .map(|&i| {
            let m = &tracker.reference().markers[i];
            offsets[m.layer] + m.id as usize
        })
        .collect();
    if used.is_empty() || used.iter().any(|&i| i >= sites.len()) {
        return Err("no marker was tracked in every frame".into());
    }
    let mm = sensor.camera.mm_per_px;
    let mut us = Vec::with_capacity(frames.len());
    for f in &frames {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        let mut u = Vec::with_capacity(2 * tracked.len());
        for &i in &tracked {
            u.push(tracks[i].displacement_px[0] * mm);
            u.push(tracks[i].displacement_px[1] * mm);
        }
        us.push(u);
    }
    // Tracking time per frame: median over reps, each after an untimed pass.
    let mut times = Vec::with_capacity(options.reps);
    let view = frames[0].view();
    for _ in 0..options.reps {
        tracker.track(&view).map_err(|e| e.to_string())?;
        let t = Instant::now();
        tracker.track(&view).map_err(|e| e.to_string())?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(Data {
        frames: us,
        used,
        truth: contact.force_grid_n(&sensor.force_grid),
        applied: contact.total_force_n(),
        track_s: Some(median(&mut times)),
    })
}
