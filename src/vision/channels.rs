//! Frames in BGR order (OpenCV's `cv2.imread`) without converting them: the tracker's
//! colour score is a weighted sum of the three channels (`window::score_weights`:
//! red weighs channel 0, green 1, blue 2; dark and bright weigh all three alike), so a
//! BGR frame measured with red and blue exchanged in the sensor's layer colours gives
//! exactly the scores, centroids and statuses of the same frame in RGB order measured
//! with the sensor as written (tested bit for bit below). The Python bindings track
//! OpenCV frames this way, at no per-frame copy.

use crate::sensor::{MarkerColor, Sensor};

/// The sensor whose layers read a BGR (or BGRA) frame as `sensor` reads the same frame
/// in RGB (RGBA) order: `red` and `blue` layer colours exchanged, everything else
/// unchanged (layer names and order, grids, camera). See the module docs.
pub fn bgr_sensor(sensor: &Sensor) -> Sensor {
    let mut s = sensor.clone();
    for layer in &mut s.layers {
        layer.color = match layer.color {
            MarkerColor::Red => MarkerColor::Blue,
            MarkerColor::Blue => MarkerColor::Red,
            c => c,
        };
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;
    use crate::sim::render::{reference_markers, render_sensor, to_rgb8};
    use crate::vision::{detect, DetectConfig, FrameView, TrackConfig, Tracker};
    use image::RgbImage;

    fn bgr(img: &RgbImage) -> RgbImage {
        let mut out = img.clone();
        for p in out.pixels_mut() {
            p.0.swap(0, 2);
        }
        out
    }

    #[test]
    fn bgr_frames_with_the_bgr_sensor_track_bit_identically_to_rgb_frames() {
        let s = paper_sensor();
        assert!(s.layers.iter().any(|l| l.color == MarkerColor::Red));
        assert!(s.layers.iter().any(|l| l.color == MarkerColor::Blue));
        let n = reference_markers(&s).len();
        let render = |shift_mm: f64| {
            let u: Vec<f64> = (0..n).flat_map(|_| [shift_mm, -0.5 * shift_mm]).collect();
            to_rgb8(&render_sensor(&s, Some(&u)).expect("paper sensor renders"))
        };
        let (reference, frame) = (render(0.0), render(0.04));
        let b = bgr_sensor(&s);
        let r_rgb = detect(&FrameView::rgb8(&reference), &s, &DetectConfig::default()).unwrap();
        let r_bgr = detect(
            &FrameView::rgb8(&bgr(&reference)),
            &b,
            &DetectConfig::default(),
        )
        .unwrap();
        assert_eq!(r_rgb.markers.len(), r_bgr.markers.len());
        for (a, c) in r_rgb.markers.iter().zip(&r_bgr.markers) {
            assert_eq!(
                (a.layer, a.id, a.centroid_px),
                (c.layer, c.id, c.centroid_px)
            );
        }
        let mut t_rgb = Tracker::new(r_rgb, TrackConfig::default());
        let mut t_bgr = Tracker::new(r_bgr, TrackConfig::default());
        let a = t_rgb.track(&FrameView::rgb8(&frame)).unwrap().to_vec();
        let c = t_bgr
            .track(&FrameView::rgb8(&bgr(&frame)))
            .unwrap()
            .to_vec();
        assert!(
            a.iter()
                .filter(|t| t.status == crate::vision::MarkerStatus::Ok)
                .count()
                > n / 2
        );
        for (x, y) in a.iter().zip(&c) {
            assert_eq!(x.status, y.status);
            assert_eq!(
                x.displacement_px.map(f64::to_bits),
                y.displacement_px.map(f64::to_bits)
            );
        }
        // The sensor as written reads the BGR frame differently (the swap matters).
        let wrong = detect(
            &FrameView::rgb8(&bgr(&reference)),
            &s,
            &DetectConfig::default(),
        );
        let same = wrong.is_ok_and(|w| {
            w.markers.len() == t_rgb.reference().markers.len()
                && w.markers
                    .iter()
                    .zip(&t_rgb.reference().markers)
                    .all(|(p, q)| p.layer == q.layer && p.centroid_px == q.centroid_px)
        });
        assert!(!same);
    }
}
