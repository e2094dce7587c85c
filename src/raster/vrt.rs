//! GDAL VRT mosaic of GeoTIFF tiles on one grid ([`write_vrt`], [`write_vrt_files`]): a small
//! XML file that GDAL, QGIS and rasterio open as one raster covering all the tiles.
//!
//! ```text
//! <VRTDataset rasterXSize=W rasterYSize=H>          W, H: the tiles' union, in cells
//!   <SRS>EPSG:code</SRS>  <GeoTransform>x0, cell, 0, y0, 0, −cell</GeoTransform>
//!   <VRTRasterBand dataType="Float32" band=b>     one per band, with NoDataValue,
//!     <ComplexSource> per tile: file (relative to the VRT when beside or below it),
//!        SourceBand, SrcRect (whole tile), DstRect (its cell offset), NODATA (so a tile's
//!        nodata never paints over a neighbour's data)
//! ```
//!
//! All tiles must share the CRS, cell size, nodata value and band count, and their origins must
//! lie on the common grid (whole cells apart); anything else is refused naming the tile.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use super::{Raster, RasterError, is_geographic_epsg, nodata_text, xml_escape};

/// What a VRT needs to know about one tile.
#[derive(Clone, Debug, PartialEq)]
pub struct VrtTile {
    /// The tile's file.
    pub path: PathBuf,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Upper-left corner x, CRS units.
    pub origin_x: f64,
    /// Upper-left corner y, CRS units.
    pub origin_y: f64,
    /// Cell side, CRS units.
    pub cell_size: f64,
    /// EPSG code of the CRS.
    pub epsg: u32,
    /// Nodata value.
    pub nodata: f32,
    /// Number of bands.
    pub bands: usize,
    /// Band names (may be empty).
    pub band_names: Vec<String>,
    /// Band units (may be empty).
    pub band_units: Vec<String>,
}

impl VrtTile {
    /// The tile `raster` written (or to be written) at `path`.
    pub fn of(path: impl Into<PathBuf>, raster: &Raster) -> VrtTile {
        VrtTile {
            path: path.into(),
            width: raster.width,
            height: raster.height,
            origin_x: raster.origin_x,
            origin_y: raster.origin_y,
            cell_size: raster.cell_size,
            epsg: raster.epsg,
            nodata: raster.nodata,
            bands: raster.bands.len(),
            band_names: raster.band_names.clone(),
            band_units: raster.band_units.clone(),
        }
    }

    /// Reads the description of a north-up Float32 GeoTIFF (as [`super::write_cog`] writes):
    /// size, tie point and pixel scale, EPSG code from the GeoKeys, `GDAL_NODATA`, band count.
    pub fn read(path: &Path) -> Result<VrtTile, RasterError> {
        use tiff::decoder::Decoder;
        use tiff::tags::Tag;
        let err = |what: String| RasterError::Read {
            file: path.display().to_string(),
            what,
        };
        let f = std::fs::File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
        let mut dec = Decoder::new(std::io::BufReader::new(f)).map_err(|e| err(e.to_string()))?;
        let (w, h) = dec.dimensions().map_err(|e| err(e.to_string()))?;
        let scale = dec
            .get_tag_f64_vec(Tag::ModelPixelScaleTag)
            .map_err(|e| err(format!("ModelPixelScaleTag: {e}")))?;
        let tie = dec
            .get_tag_f64_vec(Tag::ModelTiepointTag)
            .map_err(|e| err(format!("ModelTiepointTag: {e}")))?;
        if scale.len() < 2 || tie.len() < 6 {
            return Err(err("short ModelPixelScaleTag or ModelTiepointTag".into()));
        }
        if (scale[0] - scale[1]).abs() > 1e-9 * scale[0].abs() {
            return Err(err(format!(
                "cells are not square ({} × {})",
                scale[0], scale[1]
            )));
        }
        let keys: Vec<u8> = dec
            .get_tag_u16_vec(Tag::GeoKeyDirectoryTag)
            .map_err(|e| err(format!("GeoKeyDirectoryTag: {e}")))?
            .iter()
            .flat_map(|k| k.to_le_bytes())
            .collect();
        let epsg = crate::format::geokeys::GeoKeyDirectory::parse(&keys)
            .epsg()
            .ok_or_else(|| err("the GeoKeys name no EPSG code".into()))?;
        let nodata = match dec.get_tag_ascii_string(Tag::Unknown(42113)) {
            Ok(s) => {
                let s = s.trim_end_matches('\0').trim();
                if s.eq_ignore_ascii_case("nan") {
                    f32::NAN
                } else {
                    s.parse::<f32>()
                        .map_err(|_| err(format!("GDAL_NODATA {s:?} is not a number")))?
                }
            }
            Err(_) => return Err(err("no GDAL_NODATA tag".into())),
        };
        let bands = dec
            .get_tag_u32(Tag::SamplesPerPixel)
            .map_or(1, |s| s as usize);
        Ok(VrtTile {
            path: path.to_path_buf(),
            width: w as usize,
            height: h as usize,
            // Tie point (i, j) ↦ (x, y): the upper-left corner is x − i·sx, y + j·sy.
            origin_x: tie[3] - tie[0] * scale[0],
            origin_y: tie[4] + tie[1] * scale[1],
            cell_size: scale[0],
            epsg: u32::from(epsg),
            nodata,
            bands,
            band_names: Vec::new(),
            band_units: Vec::new(),
        })
    }
}

/// Writes a VRT mosaic of GeoTIFF files, reading each one's grid with [`VrtTile::read`].
pub fn write_vrt_files(path: &Path, tiles: &[PathBuf]) -> Result<(), RasterError> {
    let tiles = tiles
        .iter()
        .map(|t| VrtTile::read(t))
        .collect::<Result<Vec<_>, _>>()?;
    write_vrt(path, &tiles)
}

/// How a tile's file is named from the VRT: relative when beside or below the VRT's folder.
fn source_name(vrt: &Path, tile: &Path) -> (bool, String) {
    let dir = vrt.parent().unwrap_or(Path::new(""));
    if let Ok(rel) = tile.strip_prefix(dir)
        && tile.is_relative() == vrt.is_relative()
    {
        return (true, rel.display().to_string());
    }
    let abs = std::fs::canonicalize(tile).unwrap_or_else(|_| tile.to_path_buf());
    (false, abs.display().to_string())
}

/// Writes a GDAL VRT mosaic of `tiles` (all on one grid, see the module documentation) to
/// `path`, atomically. Band names and units come from the first tile that has them.
pub fn write_vrt(path: &Path, tiles: &[VrtTile]) -> Result<(), RasterError> {
    let Some(first) = tiles.first() else {
        return Err(RasterError::invalid(path, "a VRT needs at least one tile"));
    };
    check_tiles_agree(path, first, tiles)?;
    let mosaic = place_tiles(path, first, tiles)?;
    let x = vrt_xml(path, first, tiles, &mosaic);
    super::write_atomic(path, |f| f.write_all(x.as_bytes()))
}

/// Refuses (naming the tile) a tile whose CRS, cell size, nodata value or band count differs
/// from the `first` tile's, or that has no cells.
fn check_tiles_agree(path: &Path, first: &VrtTile, tiles: &[VrtTile]) -> Result<(), RasterError> {
    let cell = first.cell_size;
    let same_nodata = |a: f32, b: f32| a == b || (a.is_nan() && b.is_nan());
    for t in tiles {
        let differs = if t.epsg != first.epsg {
            Some(format!(
                "EPSG:{} (the first tile is EPSG:{})",
                t.epsg, first.epsg
            ))
        } else if (t.cell_size - cell).abs() > 1e-9 * cell {
            Some(format!(
                "cell size {} (the first tile's is {cell})",
                t.cell_size
            ))
        } else if !same_nodata(t.nodata, first.nodata) {
            Some(format!(
                "nodata {} (the first tile's is {})",
                t.nodata, first.nodata
            ))
        } else if t.bands != first.bands {
            Some(format!(
                "{} bands (the first tile has {})",
                t.bands, first.bands
            ))
        } else if t.width == 0 || t.height == 0 {
            Some("no cells".to_string())
        } else {
            None
        };
        if let Some(d) = differs {
            return Err(RasterError::invalid(
                path,
                format!("tile {} has {d}", t.path.display()),
            ));
        }
    }
    Ok(())
}

/// Where the tiles lie in the mosaic.
struct Mosaic {
    /// Upper-left corner x of the mosaic, CRS units.
    x0: f64,
    /// Upper-left corner y of the mosaic, CRS units.
    y0: f64,
    /// Columns.
    w: usize,
    /// Rows.
    h: usize,
    /// Each tile's offset from the mosaic's corner: (columns, rows).
    placed: Vec<(usize, usize)>,
}

/// Places the tiles on the `first` tile's grid: each tile's offset in whole cells from the
/// mosaic's upper-left corner, and the mosaic's size. Refuses a tile whose origin is not whole
/// cells from the first's, and a mosaic wider or taller than `MAX_DIMENSION` cells.
fn place_tiles(path: &Path, first: &VrtTile, tiles: &[VrtTile]) -> Result<Mosaic, RasterError> {
    let cell = first.cell_size;
    let x0 = tiles
        .iter()
        .map(|t| t.origin_x)
        .fold(f64::INFINITY, f64::min);
    let y0 = tiles
        .iter()
        .map(|t| t.origin_y)
        .fold(f64::NEG_INFINITY, f64::max);
    // Each tile's offset in whole cells from the mosaic's corner; the grid is the first tile's.
    let mut placed = Vec::with_capacity(tiles.len());
    let (mut w, mut h) = (0usize, 0usize);
    for t in tiles {
        let (fc, fr) = (
            (t.origin_x - first.origin_x) / cell,
            (first.origin_y - t.origin_y) / cell,
        );
        if (fc - fc.round()).abs() > 1e-6 || (fr - fr.round()).abs() > 1e-6 {
            return Err(RasterError::invalid(
                path,
                format!(
                    "tile {} origin ({}, {}) is not on the grid of the first tile {} \
                     ({fc:.6}, {fr:.6} cells from its corner)",
                    t.path.display(),
                    t.origin_x,
                    t.origin_y,
                    first.path.display()
                ),
            ));
        }
        let (c, r) = (
            ((t.origin_x - x0) / cell).round(),
            ((y0 - t.origin_y) / cell).round(),
        );
        let (c, r) = (c as usize, r as usize);
        w = w.max(c + t.width);
        h = h.max(r + t.height);
        placed.push((c, r));
    }
    if w > super::MAX_DIMENSION || h > super::MAX_DIMENSION {
        return Err(RasterError::invalid(
            path,
            format!(
                "the mosaic would be {w} × {h} cells (at most {} a side)",
                super::MAX_DIMENSION
            ),
        ));
    }
    Ok(Mosaic {
        x0,
        y0,
        w,
        h,
        placed,
    })
}

/// The VRT document (written at `path`) of `tiles` placed as `mosaic` says: size, CRS and
/// geotransform of the `first` tile's grid, then one band element per band.
fn vrt_xml(path: &Path, first: &VrtTile, tiles: &[VrtTile], mosaic: &Mosaic) -> String {
    let Mosaic { x0, y0, w, h, .. } = *mosaic;
    let cell = first.cell_size;
    let mapping = if is_geographic_epsg(first.epsg) {
        "2,1"
    } else {
        "1,2"
    };
    let mut x = String::new();
    let _ = writeln!(x, "<VRTDataset rasterXSize=\"{w}\" rasterYSize=\"{h}\">");
    let _ = writeln!(
        x,
        "  <SRS dataAxisToSRSAxisMapping=\"{mapping}\">EPSG:{}</SRS>",
        first.epsg
    );
    let _ = writeln!(
        x,
        "  <GeoTransform>{x0:?}, {cell:?}, 0.0, {y0:?}, 0.0, {:?}</GeoTransform>",
        -cell
    );
    for b in 0..first.bands {
        write_band(&mut x, path, first, tiles, &mosaic.placed, b);
    }
    let _ = writeln!(x, "</VRTDataset>");
    x
}

/// Appends to `x` the element of band `b` (0-based): its name and units (from the first tile
/// that has them), nodata value, and one source per tile at its offset in `placed`.
fn write_band(
    x: &mut String,
    path: &Path,
    first: &VrtTile,
    tiles: &[VrtTile],
    placed: &[(usize, usize)],
    b: usize,
) {
    let nodata = nodata_text(first.nodata);
    let name_of = |b: usize, field: fn(&VrtTile) -> &Vec<String>| {
        tiles
            .iter()
            .filter_map(|t| field(t).get(b))
            .find(|s| !s.is_empty())
            .cloned()
    };
    let _ = writeln!(
        x,
        "  <VRTRasterBand dataType=\"Float32\" band=\"{}\">",
        b + 1
    );
    if let Some(d) = name_of(b, |t| &t.band_names) {
        let _ = writeln!(x, "    <Description>{}</Description>", xml_escape(&d));
    }
    let _ = writeln!(x, "    <NoDataValue>{nodata}</NoDataValue>");
    if let Some(u) = name_of(b, |t| &t.band_units) {
        let _ = writeln!(x, "    <UnitType>{}</UnitType>", xml_escape(&u));
    }
    for (t, &(c, r)) in tiles.iter().zip(placed) {
        let (rel, name) = source_name(path, &t.path);
        let _ = writeln!(x, "    <ComplexSource>");
        let _ = writeln!(
            x,
            "      <SourceFilename relativeToVRT=\"{}\">{}</SourceFilename>",
            u8::from(rel),
            xml_escape(&name)
        );
        let _ = writeln!(x, "      <SourceBand>{}</SourceBand>", b + 1);
        let _ = writeln!(
            x,
            "      <SrcRect xOff=\"0\" yOff=\"0\" xSize=\"{}\" ySize=\"{}\" />",
            t.width, t.height
        );
        let _ = writeln!(
            x,
            "      <DstRect xOff=\"{c}\" yOff=\"{r}\" xSize=\"{}\" ySize=\"{}\" />",
            t.width, t.height
        );
        let _ = writeln!(x, "      <NODATA>{nodata}</NODATA>");
        let _ = writeln!(x, "    </ComplexSource>");
    }
    let _ = writeln!(x, "  </VRTRasterBand>");
}
