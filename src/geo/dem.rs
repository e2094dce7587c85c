//! A digital elevation model from a GeoTIFF: read with the `tiff` crate, located by its GeoTIFF
//! tags (ModelTiepoint + ModelPixelScale, the CRS from the GeoKey directory), sampled
//! bilinearly, with the file's nodata value honoured.
//!
//! Pixel convention: GeoTIFF's `PixelIsArea` (the default, GTRasterTypeGeoKey 1) puts the
//! tie point at the *corner* of the first pixel, so pixel (col, row) has its centre at
//! `origin + ((col + 0.5) · sx, −(row + 0.5) · sy)`; `PixelIsPoint` (2) puts it at the centre.
//! Bilinear interpolation runs between pixel centres; a sample whose four neighbours include a
//! nodata value, or that lies outside the centres' hull, is `None` (counted by the caller),
//! never a made-up height.

use std::path::Path;

use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;

/// Errors reading a DEM; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum DemError {
    /// The file cannot be opened or decoded.
    #[error("{file}: {what}")]
    Read {
        /// The file.
        file: String,
        /// What went wrong, naming the tag or field.
        what: String,
    },
    /// The DEM's CRS is not the output CRS.
    #[error(
        "{file}: the DEM is in EPSG:{dem}, the output CRS is EPSG:{output}; reproject the DEM \
         (e.g. gdalwarp -t_srs EPSG:{output}) or set the output CRS to EPSG:{dem}"
    )]
    CrsMismatch {
        /// The file.
        file: String,
        /// The DEM's EPSG code.
        dem: u32,
        /// The output CRS's EPSG code.
        output: u32,
    },
}

/// A DEM in memory.
#[derive(Clone, Debug)]
pub struct Dem {
    /// Columns, rows.
    pub size: (usize, usize),
    /// Map coordinates of the centre of pixel (0, 0).
    pub first_centre: [f64; 2],
    /// Pixel size (x, y), CRS units; rows go towards −y.
    pub pixel: [f64; 2],
    /// EPSG code of the CRS, when the GeoKeys state one.
    pub epsg: Option<u32>,
    /// The nodata value, when the file states one.
    pub nodata: Option<f32>,
    heights: Vec<f32>,
}

/// GeoKey ids used here.
const GT_RASTER_TYPE: u16 = 1025;
const PROJECTED_CS_TYPE: u16 = 3072;
const GEOGRAPHIC_TYPE: u16 = 2048;

impl Dem {
    /// A DEM from heights in memory: `size` = (columns, rows), row-major from the north-west,
    /// `first_centre` the map coordinates of pixel (0, 0)'s centre, `pixel` the pixel size
    /// (rows go towards −y). `None` when `heights` does not hold columns × rows values.
    pub fn from_heights(
        size: (usize, usize),
        first_centre: [f64; 2],
        pixel: [f64; 2],
        epsg: Option<u32>,
        heights: Vec<f32>,
    ) -> Option<Dem> {
        (size.0.checked_mul(size.1)? == heights.len()).then_some(Dem {
            size,
            first_centre,
            pixel,
            epsg,
            nodata: None,
            heights,
        })
    }

    /// Reads a single-band GeoTIFF DEM (8/16/32-bit integers or 32/64-bit floats).
    pub fn open(path: &Path) -> Result<Dem, DemError> {
        let file = path.display().to_string();
        let err = |what: String| DemError::Read {
            file: file.clone(),
            what,
        };
        let f = std::fs::File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
        let mut dec = Decoder::new(std::io::BufReader::new(f))
            .map_err(|e| err(format!("not a TIFF file: {e}")))?
            .with_limits(Limits::default());
        let (w, h) = dec
            .dimensions()
            .map_err(|e| err(format!("ImageWidth/ImageLength: {e}")))?;
        let scale = dec.get_tag_f64_vec(Tag::ModelPixelScaleTag).map_err(|e| {
            err(format!(
                "ModelPixelScaleTag (33550) missing or unreadable: {e}"
            ))
        })?;
        let tie = dec.get_tag_f64_vec(Tag::ModelTiepointTag).map_err(|e| {
            err(format!(
                "ModelTiepointTag (33922) missing or unreadable: {e}"
            ))
        })?;
        if scale.len() < 2 || tie.len() < 6 {
            return Err(err(format!(
                "ModelPixelScaleTag has {} values, ModelTiepointTag {} (need 3 and 6)",
                scale.len(),
                tie.len()
            )));
        }
        if !(scale[0] > 0.0 && scale[1] > 0.0) {
            return Err(err(format!(
                "ModelPixelScaleTag: pixel size ({}, {}) is not positive",
                scale[0], scale[1]
            )));
        }
        let keys = dec
            .get_tag_u16_vec(Tag::GeoKeyDirectoryTag)
            .unwrap_or_default();
        let key = |id: u16| -> Option<u16> {
            // Header of 4 shorts, then entries (id, location, count, value); location 0 means
            // the value is inline.
            keys.get(4..)?
                .chunks_exact(4)
                .find(|e| e[0] == id && e[1] == 0)
                .map(|e| e[3])
        };
        let pixel_is_point = key(GT_RASTER_TYPE) == Some(2);
        let epsg = key(PROJECTED_CS_TYPE)
            .or(key(GEOGRAPHIC_TYPE))
            .filter(|&c| c != 0 && c != 32767)
            .map(u32::from);
        let nodata = dec
            .get_tag_ascii_string(Tag::GdalNodata)
            .ok()
            .and_then(|s| {
                s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
                    .parse::<f32>()
                    .ok()
            });
        let data = dec
            .read_image()
            .map_err(|e| err(format!("image data: {e}")))?;
        let heights: Vec<f32> = match data {
            DecodingResult::F32(v) => v,
            DecodingResult::F64(v) => v.into_iter().map(|x| x as f32).collect(),
            DecodingResult::I16(v) => v.into_iter().map(f32::from).collect(),
            DecodingResult::U16(v) => v.into_iter().map(f32::from).collect(),
            DecodingResult::I32(v) => v.into_iter().map(|x| x as f32).collect(),
            DecodingResult::U8(v) => v.into_iter().map(f32::from).collect(),
            _ => {
                return Err(err(
                    "sample format: only 8/16/32-bit integers and floats".into()
                ));
            }
        };
        let (w, h) = (w as usize, h as usize);
        if heights.len() != w * h {
            return Err(err(format!(
                "{} samples for {w} x {h} pixels: one band expected (SamplesPerPixel 1)",
                heights.len()
            )));
        }
        // Tie point (i, j) ↔ (x, y): the map position of raster position (i, j).
        let corner = [tie[3] - tie[0] * scale[0], tie[4] + tie[1] * scale[1]];
        let half = if pixel_is_point { 0.0 } else { 0.5 };
        Ok(Dem {
            size: (w, h),
            first_centre: [corner[0] + half * scale[0], corner[1] - half * scale[1]],
            pixel: [scale[0], scale[1]],
            epsg,
            nodata,
            heights,
        })
    }

    /// Refuses a DEM whose CRS is not `output_epsg` (a DEM stating no CRS is accepted as is,
    /// with a warning).
    pub fn check_crs(&self, file: &str, output_epsg: u32) -> Result<(), DemError> {
        match self.epsg {
            Some(d) if d != output_epsg => Err(DemError::CrsMismatch {
                file: file.to_string(),
                dem: d,
                output: output_epsg,
            }),
            Some(_) => Ok(()),
            None => {
                tracing::warn!(
                    file,
                    "the DEM states no CRS; taken to be EPSG:{output_epsg}"
                );
                Ok(())
            }
        }
    }

    fn at(&self, col: usize, row: usize) -> Option<f32> {
        let v = *self.heights.get(row * self.size.0 + col)?;
        (v.is_finite() && Some(v) != self.nodata).then_some(v)
    }

    /// The height at map position (`x`, `y`), bilinear between the four nearest pixel centres;
    /// `None` outside the DEM or next to nodata.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let fx = (x - self.first_centre[0]) / self.pixel[0];
        let fy = (self.first_centre[1] - y) / self.pixel[1];
        let (w, h) = (self.size.0 as f64, self.size.1 as f64);
        if !(fx >= 0.0 && fy >= 0.0 && fx <= w - 1.0 && fy <= h - 1.0) {
            return None;
        }
        let c0 = (fx.floor() as usize).min(self.size.0.saturating_sub(2));
        let r0 = (fy.floor() as usize).min(self.size.1.saturating_sub(2));
        let (c1, r1) = ((c0 + 1).min(self.size.0 - 1), (r0 + 1).min(self.size.1 - 1));
        let (tx, ty) = (fx - c0 as f64, fy - r0 as f64);
        let z00 = self.at(c0, r0)? as f64;
        let z10 = self.at(c1, r0)? as f64;
        let z01 = self.at(c0, r1)? as f64;
        let z11 = self.at(c1, r1)? as f64;
        Some(
            z00 * (1.0 - tx) * (1.0 - ty)
                + z10 * tx * (1.0 - ty)
                + z01 * (1.0 - tx) * ty
                + z11 * tx * ty,
        )
    }
}

impl Dem {
    /// Height above the DEM of every bin of a segment: bin `i` lies `first_ns + i · sample_ns`
    /// after the pulse's t0 at `anchor + t · direction` (in the DEM's CRS); `out[i]` gets its
    /// height above the DEM there, metres, or NaN outside the DEM or next to nodata. Returns how
    /// many bins got a height.
    pub fn heights_above_ground(
        &self,
        geometry: &crate::pulse::PulseGeometry,
        first_ns: f64,
        sample_ns: f64,
        out: &mut [f64],
    ) -> usize {
        let mut placed = 0;
        for (i, h) in out.iter_mut().enumerate() {
            let t = first_ns + i as f64 * sample_ns;
            let [x, y, z] = [0, 1, 2].map(|k| geometry.anchor[k] + t * geometry.direction[k]);
            *h = match self.height_at(x, y) {
                Some(g) => {
                    placed += 1;
                    z - g
                }
                None => f64::NAN,
            };
        }
        placed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dem(heights: Vec<f32>, w: usize, h: usize) -> Dem {
        Dem {
            size: (w, h),
            first_centre: [100.25, 199.75],
            pixel: [0.5, 0.5],
            epsg: Some(2154),
            nodata: Some(-9999.0),
            heights,
        }
    }

    /// Heights z = 2x − 3y at the centres of a `w` × `h` grid laid out as `dem` lays it.
    fn plane(w: usize, h: usize) -> Vec<f32> {
        let mut v = Vec::new();
        for r in 0..h {
            for c in 0..w {
                let (x, y) = (100.25 + 0.5 * c as f64, 199.75 - 0.5 * r as f64);
                v.push((2.0 * x - 3.0 * y) as f32);
            }
        }
        v
    }

    #[test]
    fn every_bin_of_a_slanted_beam_gets_its_height_above_a_plane() {
        // DEM z = 2x − 3y over its centres; a beam from (100.5, 199.5, 10) going down and east.
        let (w, h) = (4, 3);
        let v = plane(w, h);
        let d = dem(v, w, h);
        let g = crate::pulse::PulseGeometry {
            anchor: [100.5, 199.5, 10.0],
            direction: [0.01, 0.0, -0.15],
        };
        let mut out = [0.0; 200];
        let n = d.heights_above_ground(&g, 0.0, 1.0, &mut out);
        // x leaves the centres' hull (101.75) after 125 bins.
        assert_eq!(n, 126);
        for (i, hag) in out.iter().enumerate().take(126) {
            let t = i as f64;
            let (x, y, z) = (100.5 + 0.01 * t, 199.5, 10.0 - 0.15 * t);
            assert!((hag - (z - (2.0 * x - 3.0 * y))).abs() < 1e-3, "{i}: {hag}");
        }
        assert!(out[126..].iter().all(|h| h.is_nan()));
    }

    #[test]
    fn bilinear_reproduces_a_plane_and_respects_nodata_and_edges() {
        // z = 2x − 3y sampled at the centres: bilinear is exact on a plane.
        let (w, h) = (4, 3);
        let v = plane(w, h);
        let d = dem(v.clone(), w, h);
        let z = d.height_at(101.1, 199.1).unwrap();
        assert!((z - (2.0 * 101.1 - 3.0 * 199.1)).abs() < 1e-3, "{z}");
        assert!(d.height_at(100.0, 199.0).is_none(), "outside the centres");
        assert!(d.height_at(f64::NAN, 199.0).is_none());
        let mut holes = v;
        holes[5] = -9999.0;
        let d = dem(holes, w, h);
        assert!(d.height_at(100.9, 199.4).is_none(), "next to nodata");
        assert!(d.height_at(101.6, 198.9).is_some(), "away from it");
        assert!(d.check_crs("x.tif", 2154).is_ok());
        let e = d.check_crs("x.tif", 32633).unwrap_err().to_string();
        assert!(
            e.contains("x.tif") && e.contains("EPSG:2154") && e.contains("EPSG:32633"),
            "{e}"
        );
    }
}
