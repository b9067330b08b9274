//! NumPy arrays as frames: `uint8` / `uint16`, H×W (greyscale: `dark` / `bright`
//! layers only, the library refuses coloured ones), H×W×3 or H×W×4 (RGB(A), or BGR(A) read
//! through [`crate::vision::bgr_sensor`]), C-contiguous borrowed as is, any other
//! layout copied once. Everything else is a `ValueError` saying what was found and
//! what is accepted: other dtypes (floats, so NaN and infinite pixels, included),
//! other shapes, empty arrays, a size other than the sensor's `[camera]`.

use numpy::{
    PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use super::value_error;
use crate::sensor::Sensor;
use crate::vision::{FrameView, Pixels};

/// Channel order of 3- and 4-channel frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Order {
    Rgb,
    Bgr,
}

/// `channels=`: `None`, `"rgb"` or `"bgr"`.
pub(crate) fn parse_order(channels: Option<&str>) -> PyResult<Option<Order>> {
    match channels {
        None => Ok(None),
        Some("rgb") => Ok(Some(Order::Rgb)),
        Some("bgr") => Ok(Some(Order::Bgr)),
        Some(other) => Err(value_error(format!(
            "channels={other:?}: expected \"rgb\" or \"bgr\" (OpenCV's cv2.imread order)"
        ))),
    }
}

/// The sensor's layers told apart by colour (blue, red, green), as `name (color)`.
pub(crate) fn coloured_layers(sensor: &Sensor) -> Vec<String> {
    sensor
        .layers
        .iter()
        .filter(|l| !l.color.is_brightness())
        .map(|l| format!("layer {:?} (color {})", l.name, l.color))
        .collect()
}

enum Samples<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    U16(PyReadonlyArrayDyn<'py, u16>),
    OwnedU8(Vec<u8>),
    OwnedU16(Vec<u16>),
}

/// A frame taken from a NumPy array (borrowed when C-contiguous).
pub(crate) struct FrameInput<'py> {
    samples: Samples<'py>,
    width_px: u32,
    height_px: u32,
    channels: usize,
}

impl<'py> FrameInput<'py> {
    /// Checks dtype, shape and size (`what` names the array in errors).
    pub(crate) fn extract(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<Self> {
        let untyped = obj.cast::<PyUntypedArray>().map_err(|_| {
            value_error(format!(
                "{what}: expected a NumPy array (uint8 or uint16, H×W, H×W×3 or H×W×4), got {}",
                obj.get_type()
                    .name()
                    .map(|n| n.to_string())
                    .unwrap_or_else(|_| "an object".into())
            ))
        })?;
        let shape = untyped.shape();
        // Only error messages need the shape and dtype as text: built on failure only,
        // so a frame costs no Python call beyond the casts.
        let shape_text = || {
            format!(
                "({})",
                shape
                    .iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        };
        if shape.contains(&0) {
            return Err(value_error(format!(
                "{what}: empty array of shape {}: a frame needs pixels",
                shape_text()
            )));
        }
        let channels = match shape {
            [_, _] => 1,
            [_, _, c @ (3 | 4)] => *c,
            _ => {
                return Err(value_error(format!(
                    "{what}: shape {}: expected H×W (greyscale), H×W×3 or H×W×4 (RGB(A) or BGR(A))",
                    shape_text()
                )));
            }
        };
        let (height, width) = (shape[0], shape[1]);
        let too_big = |d: usize| u32::try_from(d).is_err();
        if too_big(height) || too_big(width) {
            return Err(value_error(format!(
                "{what}: shape {} is too large",
                shape_text()
            )));
        }
        let samples = if let Ok(a) = obj.cast::<PyArrayDyn<u8>>() {
            let r = a
                .try_readonly()
                .map_err(|e| value_error(format!("{what}: {e}")))?;
            // `as_slice` also accepts Fortran order: only C order is read in place.
            if a.is_c_contiguous() {
                Samples::U8(r)
            } else {
                Samples::OwnedU8(r.as_array().iter().copied().collect())
            }
        } else if let Ok(a) = obj.cast::<PyArrayDyn<u16>>() {
            let r = a
                .try_readonly()
                .map_err(|e| value_error(format!("{what}: {e}")))?;
            if a.is_c_contiguous() {
                Samples::U16(r)
            } else {
                Samples::OwnedU16(r.as_array().iter().copied().collect())
            }
        } else {
            return Err(value_error(format!(
                "{what}: dtype {}: expected uint8 or uint16 pixels (8- or 16-bit, native byte order); convert floats with e.g. numpy.clip(img, 0, 255).astype(numpy.uint8) after checking for NaN",
                untyped.dtype()
            )));
        };
        Ok(FrameInput {
            samples,
            width_px: width as u32,
            height_px: height as u32,
            channels,
        })
    }

    /// Width, height, px.
    pub(crate) fn size(&self) -> [u32; 2] {
        [self.width_px, self.height_px]
    }

    /// Samples per pixel (1, 3 or 4).
    pub(crate) fn channels(&self) -> usize {
        self.channels
    }

    /// The library's view of the samples.
    pub(crate) fn view(&self) -> PyResult<FrameView<'_>> {
        fn u8s(d: &[u8], channels: usize) -> Pixels<'_> {
            match channels {
                1 => Pixels::Gray8(d),
                3 => Pixels::Rgb8(d),
                _ => Pixels::Rgba8(d),
            }
        }
        fn u16s(d: &[u16], channels: usize) -> Pixels<'_> {
            match channels {
                1 => Pixels::Gray16(d),
                3 => Pixels::Rgb16(d),
                _ => Pixels::Rgba16(d),
            }
        }
        let pixels = match &self.samples {
            Samples::U8(a) => u8s(
                a.as_slice().map_err(|e| value_error(e.to_string()))?,
                self.channels,
            ),
            Samples::OwnedU8(v) => u8s(v, self.channels),
            Samples::U16(a) => u16s(
                a.as_slice().map_err(|e| value_error(e.to_string()))?,
                self.channels,
            ),
            Samples::OwnedU16(v) => u16s(v, self.channels),
        };
        FrameView::new(pixels, self.width_px, self.height_px).map_err(|e| super::to_py_err(&e))
    }
}
