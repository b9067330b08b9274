//! The simulated sensor: a sensor, an indenter and an effect pipeline; renders the
//! camera frame for any load, with the ground truth (marker displacements, force-grid
//! forces). Used by `tactbench sim render` through [`Simulation::from_scene`], and
//! meant for the simulated camera of the virtual bench through [`Simulation::new`] +
//! [`Simulation::render_load`].
//!
//! Per frame: contact model → cell forces → elastic displacements (the half-space of
//! paper Eq. 1–2, or the bonded layer a scene's `[physics] model` selects; with u_z)
//! at the (built) marker positions → camera optics (only with the camera effects
//! `perspective`, `refraction`, `lens_distortion`: each marker's centre projected from
//! its depth and `u_z`, see [`super::camera`]) → image offset (shift, drift) → rasterisation → image effects.

use image::Rgb32FImage;
use thiserror::Error;

use super::camera::CameraOptics;
use super::contact::{Contact, ContactError, Indenter, LoadCase};
use super::effects::{Pipeline, Scratch};
use super::render::{reference_markers, Marker, PixelFilter, RenderError, Renderer};
use super::scene::Scene;
use crate::model::{ElasticModel, ForwardModel, HalfSpace, MarkerSite};
use crate::sensor::{ModelKind, Sensor};

/// An error simulating a frame.
#[derive(Debug, Error, PartialEq)]
pub enum SimError {
    /// The contact could not be solved.
    #[error("contact: {0}")]
    Contact(#[from] ContactError),
    /// The frame could not be rendered.
    #[error("render: {0}")]
    Render(#[from] RenderError),
}

/// Ground truth of one rendered frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTruth {
    /// Pipeline frame index (0 = reference, loaded frames 1, 2, …).
    pub frame: u64,
    /// The solved contact (`None` for the unloaded reference).
    pub contact: Option<Contact>,
    /// Elastic marker displacements (interleaved `ux, uy`, mm), marker order of
    /// [`Simulation::markers`].
    pub elastic_u_mm: Vec<f64>,
    /// Elastic out-of-plane displacements `u_z` (mm, positive into the elastomer), one
    /// per marker in the order of [`Simulation::markers`].
    pub elastic_uz_mm: Vec<f64>,
    /// Whole-image offset of this frame (shift + drift), px.
    pub offset_px: [f64; 2],
    /// Force-grid truth (interleaved `fx, fy, fz` per node, N; zeros for the reference).
    pub forces_n: Vec<f64>,
}

impl FrameTruth {
    /// Apparent displacement of marker `k` in the image, px: elastic displacement plus
    /// the image offset (what an ideal tracker measures against the reference frame,
    /// whose offset is subtracted).
    pub fn apparent_u_px(
        &self,
        k: usize,
        mm_per_px: f64,
        reference_offset_px: [f64; 2],
    ) -> [f64; 2] {
        [
            self.elastic_u_mm[2 * k] / mm_per_px + self.offset_px[0] - reference_offset_px[0],
            self.elastic_u_mm[2 * k + 1] / mm_per_px + self.offset_px[1] - reference_offset_px[1],
        ]
    }
}

/// A simulated sensor under an indenter.
#[derive(Debug)]
pub struct Simulation {
    sensor: Sensor,
    /// Material for the contact model (Hertz, punch).
    model: HalfSpace,
    /// What renders the marker displacements.
    elastic: ForwardModel,
    indenter: Indenter,
    pipeline: Pipeline,
    renderer: Renderer,
    markers: Vec<Marker>,
    ids: Vec<(usize, usize)>,
    sites: Vec<MarkerSite>,
    scratch: Scratch,
    moved: Vec<Marker>,
    /// The camera effects (`None`: the linear `[camera]` mapping).
    optics: Option<CameraOptics>,
}

impl Simulation {
    /// A simulation of `sensor`'s grid markers (build effects applied once here).
    pub fn new(sensor: Sensor, indenter: Indenter, pipeline: Pipeline) -> Self {
        let mut markers = reference_markers(&sensor);
        let mut ids = Vec::with_capacity(markers.len());
        for (li, l) in sensor.layers.iter().enumerate() {
            if let Some(m) = &l.markers {
                ids.extend((0..m.grid.len()).map(|k| (li, k)));
            }
        }
        pipeline.build_markers(&mut markers);
        let sites = markers
            .iter()
            .map(|m| MarkerSite {
                layer: m.layer,
                position_mm: m.position_mm,
                depth_mm: sensor.layers[m.layer].depth_mm,
            })
            .collect();
        let model = HalfSpace::from_elastomer(&sensor.elastomer);
        let optics = CameraOptics::from_pipeline(&pipeline, &sensor);
        Simulation {
            optics,
            model,
            elastic: ForwardModel::HalfSpace(model),
            renderer: Renderer::new(&sensor),
            sensor,
            indenter,
            pipeline,
            markers,
            ids,
            sites,
            scratch: Scratch::default(),
            moved: Vec::new(),
        }
    }

    /// The simulation of a scene (with its pixel filter).
    pub fn from_scene(scene: &Scene) -> Self {
        Self::new(scene.sensor.clone(), scene.indenter, scene.pipeline.clone())
            .with_pixel_filter(scene.pixel_filter)
            .with_physics(scene.physics)
    }

    /// This simulation rendering with the elastic model `kind` on the sensor's
    /// material and thickness (the default is the half-space).
    pub fn with_physics(mut self, kind: ModelKind) -> Self {
        self.elastic = ForwardModel::of_kind(kind, &self.sensor.elastomer);
        let depths: Vec<f64> = self.sites.iter().map(|s| s.depth_mm).collect();
        // Tables for the marker depths over the camera's field (built once here).
        let (w, h) = (
            self.sensor.camera.width_px as f64,
            self.sensor.camera.height_px as f64,
        );
        let diag = w.hypot(h) * self.sensor.camera.mm_per_px;
        self.elastic.prepare(&depths, 2.0 * diag);
        self
    }

    /// The elastic model that renders the marker displacements.
    pub fn elastic_model(&self) -> &ForwardModel {
        &self.elastic
    }

    /// This simulation with another pixel response (see [`PixelFilter`]).
    pub fn with_pixel_filter(mut self, filter: PixelFilter) -> Self {
        self.renderer = self.renderer.with_filter(filter);
        self
    }

    /// The sensor.
    pub fn sensor(&self) -> &Sensor {
        &self.sensor
    }

    /// The effect pipeline.
    pub fn pipeline(&self) -> &Pipeline {
        &self.pipeline
    }

    /// The renderer (camera, palette, drawing order).
    pub fn renderer(&self) -> &Renderer {
        &self.renderer
    }

    /// The markers at their reference positions (after size and placement jitter).
    pub fn markers(&self) -> &[Marker] {
        &self.markers
    }

    /// `(layer index, marker id)` of each marker; the id is the row-major index in its
    /// layer's grid.
    pub fn marker_ids(&self) -> &[(usize, usize)] {
        &self.ids
    }

    /// A frame buffer of the camera's size.
    pub fn blank_frame(&self) -> Rgb32FImage {
        self.renderer.blank()
    }

    /// The camera optics of the scene's camera effects (`None` when none is listed).
    pub fn optics(&self) -> Option<&CameraOptics> {
        self.optics.as_ref()
    }

    /// Where the centre of marker `k` appears in the frame of `truth`, px: its
    /// displaced position seen through the camera optics (or the linear `[camera]`
    /// mapping), plus the frame's image offset.
    pub fn apparent_px(&self, k: usize, truth: &FrameTruth) -> [f64; 2] {
        let m = &self.markers[k];
        let p = [
            m.position_mm[0] + truth.elastic_u_mm[2 * k],
            m.position_mm[1] + truth.elastic_u_mm[2 * k + 1],
        ];
        let q = match &self.optics {
            None => self.renderer.camera().mm_to_px(p),
            Some(o) => {
                o.project(p, self.sites[k].depth_mm + truth.elastic_uz_mm[k])
                    .0
            }
        };
        [q[0] + truth.offset_px[0], q[1] + truth.offset_px[1]]
    }

    /// Replaces each marker of `self.moved` (sensor-frame mm, marker order) by the disc
    /// the camera optics show, expressed in the renderer's linear mapping: centre at
    /// the projected pixel position, diameter scaled by the local magnification.
    fn project_moved(&mut self, uz_mm: Option<&[f64]>) {
        let Some(optics) = &self.optics else {
            return;
        };
        let cam = *self.renderer.camera();
        for (k, m) in self.moved.iter_mut().enumerate() {
            let z = self.sites[k].depth_mm + uz_mm.map_or(0.0, |u| u[k]);
            let (p_px, px_per_mm) = optics.project(m.position_mm, z);
            m.position_mm = cam.px_to_mm(p_px);
            m.diameter_mm *= px_per_mm * cam.mm_per_px;
        }
    }

    /// Renders the unloaded reference frame (pipeline frame 0) into `out`.
    pub fn render_reference(&mut self, out: &mut Rgb32FImage) -> Result<FrameTruth, SimError> {
        if self.optics.is_some() {
            self.moved.clear();
            self.moved.extend_from_slice(&self.markers);
            self.project_moved(None);
            self.pipeline
                .render_frame(&self.renderer, &self.moved, 0, out, &mut self.scratch)?;
        } else {
            self.pipeline
                .render_frame(&self.renderer, &self.markers, 0, out, &mut self.scratch)?;
        }
        Ok(FrameTruth {
            frame: 0,
            contact: None,
            elastic_u_mm: vec![0.0; 2 * self.markers.len()],
            elastic_uz_mm: vec![0.0; self.markers.len()],
            offset_px: self.pipeline.image_offset_px(0),
            forces_n: vec![0.0; 3 * self.sensor.force_grid.len()],
        })
    }

    /// Renders pipeline frame `frame` (≥ 1 for loaded frames) under `load` into `out`.
    pub fn render_load(
        &mut self,
        load: &LoadCase,
        frame: u64,
        out: &mut Rgb32FImage,
    ) -> Result<FrameTruth, SimError> {
        self.render_load_shifted(load, frame, [0.0, 0.0], out)
    }

    /// As [`Simulation::render_load`], with every marker also moved by `shift_mm` (the
    /// whole sensor shifted under the camera, e.g. by a stage that carries it). The
    /// truth's `elastic_u_mm` excludes the shift.
    pub fn render_load_shifted(
        &mut self,
        load: &LoadCase,
        frame: u64,
        shift_mm: [f64; 2],
        out: &mut Rgb32FImage,
    ) -> Result<FrameTruth, SimError> {
        let contact = Contact::solve(&self.model, self.indenter, load)?;
        let (u, uz) = self.marker_displacements(&contact);
        self.moved.clear();
        self.moved
            .extend(self.markers.iter().enumerate().map(|(k, m)| Marker {
                position_mm: [
                    m.position_mm[0] + u[2 * k] + shift_mm[0],
                    m.position_mm[1] + u[2 * k + 1] + shift_mm[1],
                ],
                ..*m
            }));
        self.project_moved(Some(&uz));
        self.pipeline
            .render_frame(&self.renderer, &self.moved, frame, out, &mut self.scratch)?;
        let forces_n = contact.force_grid_n(&self.sensor.force_grid);
        Ok(FrameTruth {
            frame,
            contact: Some(contact),
            elastic_u_mm: u,
            elastic_uz_mm: uz,
            offset_px: self.pipeline.image_offset_px(frame),
            forces_n,
        })
    }

    /// Marker displacements of a solved contact: interleaved `ux, uy` and `uz` (mm).
    /// For the half-space the horizontal part is bit-identical to
    /// [`Contact::marker_displacements_mm`] (same terms, same order).
    fn marker_displacements(&self, contact: &Contact) -> (Vec<f64>, Vec<f64>) {
        let mut u = vec![0.0; 2 * self.sites.len()];
        let mut uz = vec![0.0; self.sites.len()];
        for (k, s) in self.sites.iter().enumerate() {
            let mut acc = [0.0; 3];
            for l in &contact.loads {
                let h = self.elastic.point_response3(
                    s.position_mm[0] - l.position_mm[0],
                    s.position_mm[1] - l.position_mm[1],
                    s.depth_mm,
                );
                let f = l.force_n;
                for (a, acc) in acc.iter_mut().enumerate() {
                    *acc += h[a][0] * f[0] + h[a][1] * f[1] + h[a][2] * f[2];
                }
            }
            u[2 * k] = acc[0];
            u[2 * k + 1] = acc[1];
            uz[k] = acc[2];
        }
        (u, uz)
    }
}
