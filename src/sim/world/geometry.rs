//! The scene's geometry and ray tracing in the scene frame (metres east, north, up).
//!
//! A ray meets **solid** surfaces (terrain, stems, branches, boxes, roofs and walls), which
//! stop it, and **turbid media** (leafy crowns, grass layers), which it crosses while losing
//! energy by Beer-Lambert: through a path `ℓ` in a medium of leaf area density `u` (m²/m³) and
//! projection function `G`, the fraction `exp(−G u ℓ)` passes. [`Scene::trace`] returns what a
//! ray meets up to the first solid hit, as [`Hit`]s and [`MediumSpan`]s sorted by range.
//!
//! Objects are found through a uniform horizontal grid of cells (their bounding boxes), so a
//! ray tests only the objects whose cells its path crosses between the highest object top and
//! the lowest terrain.

use std::path::Path;

use crate::geo::dem::Dem;
use crate::sim::analytic_scene::SceneError;

use super::scene::{self as cfg, CrownShape, Ridge, WorldScene};

/// A 3-vector in the scene frame.
pub type V3 = [f64; 3];

fn add(a: V3, s: f64, d: V3) -> V3 {
    [a[0] + s * d[0], a[1] + s * d[1], a[2] + s * d[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
/// `v / |v|`.
pub fn normalize(v: V3) -> V3 {
    let n = dot(v, v).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

/// What an object is (for the truth).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObjectKind {
    /// The terrain.
    Terrain,
    /// A tree's stem.
    Stem,
    /// A tree's branch.
    Branch,
    /// A tree's leafy crown (medium).
    Crown,
    /// A grass patch (medium).
    Grass,
    /// A box.
    Box,
    /// A gable roof plane.
    Roof,
    /// A wall.
    Wall,
}

impl ObjectKind {
    /// Name in truth files.
    pub fn name(self) -> &'static str {
        match self {
            ObjectKind::Terrain => "terrain",
            ObjectKind::Stem => "stem",
            ObjectKind::Branch => "branch",
            ObjectKind::Crown => "crown",
            ObjectKind::Grass => "grass",
            ObjectKind::Box => "box",
            ObjectKind::Roof => "roof",
            ObjectKind::Wall => "wall",
        }
    }
}

/// A solid surface met by a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Range along the ray, metres.
    pub range_m: f64,
    /// Reflectance, 0..1.
    pub reflectance: f64,
    /// |cos| of the angle between the ray and the surface normal.
    pub cos_incidence: f64,
    /// What was hit.
    pub kind: ObjectKind,
    /// Index of the object among those of its kind in the scene file (tree index for stems,
    /// branches and crowns).
    pub object: u32,
}

/// A stretch of turbid medium crossed by a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MediumSpan {
    /// Range where the ray enters, metres.
    pub enter_m: f64,
    /// Range where it leaves (or is stopped), metres.
    pub exit_m: f64,
    /// Extinction coefficient `G u`, per metre of path.
    pub extinction_per_m: f64,
    /// Reflectance of the leaves.
    pub reflectance: f64,
    /// What it is.
    pub kind: ObjectKind,
    /// Its index (tree or grass patch).
    pub object: u32,
}

enum Ground {
    /// z = h0 + gx·x + gy·y.
    Plane { h0: f64, gx: f64, gy: f64 },
    /// A DEM: scene (e, n) is DEM (e + cx, n + cy); heights minus `datum`.
    Dem {
        dem: Box<Dem>,
        cx: f64,
        cy: f64,
        datum: f64,
        min: f64,
        max: f64,
        step: f64,
    },
}

/// A convex volume of leaves.
#[derive(Clone, Debug)]
enum Envelope {
    Ellipsoid {
        c: V3,
        r: f64,
        rz: f64,
    },
    Cone {
        c: [f64; 2],
        base: f64,
        top: f64,
        r: f64,
    },
    Cylinder {
        c: [f64; 2],
        base: f64,
        top: f64,
        r: f64,
    },
    /// A layer `lo..hi` above a ground plane `z = h0 + gx x + gy y`, over a rectangle.
    Layer {
        rect: [f64; 4],
        h0: f64,
        gx: f64,
        gy: f64,
        lo: f64,
        hi: f64,
    },
}

#[derive(Clone, Debug)]
enum Shape {
    /// Finite cylinder from `p0` along unit `axis` for `len`, radius `r` (no caps).
    Cylinder { p0: V3, axis: V3, len: f64, r: f64 },
    /// Axis-aligned box.
    Aabb { lo: V3, hi: V3 },
    /// A plane `z = h0 + gx x + gy y` over the rectangle.
    RoofPlane {
        rect: [f64; 4],
        h0: f64,
        gx: f64,
        gy: f64,
    },
    /// A medium.
    Medium { env: Envelope, extinction: f64 },
}

#[derive(Clone, Debug)]
struct Object {
    shape: Shape,
    reflectance: f64,
    kind: ObjectKind,
    index: u32,
    /// Bounding box.
    lo: V3,
    hi: V3,
}

/// The traced scene.
pub struct Scene {
    ground: Ground,
    ground_reflectance: f64,
    objects: Vec<Object>,
    cell_m: f64,
    grid_lo: [f64; 2],
    grid_n: [usize; 2],
    cells: Vec<Vec<u32>>,
    top_z: f64,
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene")
            .field("objects", &self.objects.len())
            .field("cells", &self.grid_n)
            .finish()
    }
}

/// Scratch for one ray (reused: tracing allocates nothing once warm).
#[derive(Debug, Default)]
pub struct TraceScratch {
    /// Solid hits, sorted by range; the first one stops the ray.
    pub hits: Vec<Hit>,
    /// Media crossed before the first solid hit, sorted by entry.
    pub media: Vec<MediumSpan>,
    stamp: Vec<u32>,
    ray: u32,
}

/// A small deterministic generator for layouts (SplitMix64), independent of the noise streams.
fn splitmix(state: &mut u64) -> f64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

/// Every first-order branch of tree number `index` (listed trees first, then each stand's, as
/// [`Scene::build`] numbers them) of a scene with `seed`: its listed `branches`, then its
/// `branch_count` generated ones (heights spread over the lower 80 % of the crown, zenith
/// 50–70°, azimuths a golden angle apart with a random offset, reaching the crown's edge).
/// The simulator traces exactly these; `fwlidar simulate` writes them as the branch truth.
pub fn tree_branches(seed: u64, index: u32, t: &cfg::Tree) -> Vec<cfg::Branch> {
    let depth = t.height_m - t.crown.base_m;
    let mut branches = t.branches.clone();
    let mut rng = seed ^ (0xB4A2_C0DE_u64.wrapping_mul(u64::from(index) + 1));
    for k in 0..t.branch_count {
        let f = (k as f64 + 0.5) / t.branch_count as f64;
        let h = t.crown.base_m + f * 0.8 * depth;
        let zen = 50.0 + 20.0 * splitmix(&mut rng);
        let az = (k as f64 * 137.507_764 + 360.0 * splitmix(&mut rng)).rem_euclid(360.0);
        let reach = crown_radius_at(&t.crown, t.height_m, h).max(t.crown.radius_m * 0.3);
        branches.push(cfg::Branch {
            height_m: h,
            azimuth_deg: az,
            zenith_deg: zen,
            length_m: reach / zen.to_radians().sin(),
            radius_m: t.branch_radius_m,
        });
    }
    branches
}

impl Scene {
    /// Builds the traced scene from its description (`base_dir`: where relative paths start).
    pub fn build(s: &WorldScene, base_dir: &Path) -> Result<Scene, SceneError> {
        let (ground, ground_reflectance) = ground_of(s, base_dir)?;
        let mut scene = Scene {
            ground,
            ground_reflectance,
            objects: Vec::new(),
            cell_m: 8.0,
            grid_lo: [0.0; 2],
            grid_n: [0; 2],
            cells: Vec::new(),
            top_z: f64::NEG_INFINITY,
        };
        let mut objects = Vec::new();
        // Listed trees first, then each forest's, numbered on.
        let mut trees = s.tree.clone();
        for (i, f) in s.forest.iter().enumerate() {
            trees.extend(f.trees(s.seed, i));
        }
        for (i, t) in trees.iter().enumerate() {
            scene.push_tree(s, i as u32, t, &mut objects);
        }
        for (i, g) in s.grass.iter().enumerate() {
            if g.leaf_area_density <= 0.0 {
                continue;
            }
            objects.push(scene.grass_object(s, i as u32, g));
        }
        for (i, b) in s.boxes.iter().enumerate() {
            objects.push(scene.box_object(s, i as u32, b));
        }
        for (i, b) in s.roof.iter().enumerate() {
            scene.push_roof(s, i as u32, b, &mut objects);
        }
        scene.index(objects);
        Ok(scene)
    }

    /// Tree number `i`'s objects onto `objects`: its stem (when its radius is > 0), its
    /// branches ([`tree_branches`]) and its leafy crown (when its leaf area density is > 0),
    /// standing on the ground at its position.
    fn push_tree(&self, s: &WorldScene, i: u32, t: &cfg::Tree, objects: &mut Vec<Object>) {
        let [x, y] = t.position_m;
        let z0 = self.ground_height(x, y).unwrap_or(0.0);
        let top = z0 + t.height_m;
        if t.stem_radius_m > 0.0 {
            objects.push(cylinder(
                [x, y, z0],
                [0.0, 0.0, 1.0],
                t.height_m,
                t.stem_radius_m,
                refl(s, &t.bark),
                ObjectKind::Stem,
                i,
            ));
        }
        let cb = z0 + t.crown.base_m;
        for b in &tree_branches(s.seed, i, t) {
            let (z, a) = (b.zenith_deg.to_radians(), b.azimuth_deg.to_radians());
            objects.push(cylinder(
                [x, y, z0 + b.height_m],
                [z.sin() * a.sin(), z.sin() * a.cos(), z.cos()],
                b.length_m,
                b.radius_m,
                refl(s, &t.bark),
                ObjectKind::Branch,
                i,
            ));
        }
        if t.leaf_area_density > 0.0 {
            let r = t.crown.radius_m;
            objects.push(Object {
                shape: Shape::Medium {
                    env: crown_envelope(t.crown.shape, [x, y], cb, top, r),
                    extinction: t.g_function * t.leaf_area_density,
                },
                reflectance: refl(s, &t.leaf),
                kind: ObjectKind::Crown,
                index: i,
                lo: [x - r, y - r, cb],
                hi: [x + r, y + r, top],
            });
        }
    }

    /// The ground plane `(h0, gx, gy)` (`z = h0 + gx x + gy y`, metres) a layer over `rect`
    /// stands on: the terrain's plane, or over a DEM the level plane at the height of the
    /// rectangle's centre.
    fn plane_of_ground(&self, rect: &[f64; 4]) -> (f64, f64, f64) {
        match &self.ground {
            Ground::Plane { h0, gx, gy } => (*h0, *gx, *gy),
            Ground::Dem { .. } => (self.base_of(rect), 0.0, 0.0),
        }
    }

    /// The terrain's height at the centre of `r` (`[west, south, east, north]`), metres; 0
    /// outside a DEM.
    fn base_of(&self, r: &[f64; 4]) -> f64 {
        self.ground_height((r[0] + r[2]) / 2.0, (r[1] + r[3]) / 2.0)
            .unwrap_or(0.0)
    }

    /// Grass patch number `i`: a layer of leaves `height_m` thick over its rectangle,
    /// following the ground's plane.
    fn grass_object(&self, s: &WorldScene, i: u32, g: &cfg::Grass) -> Object {
        let (h0, gx, gy) = self.plane_of_ground(&g.rectangle_m);
        let r = g.rectangle_m;
        let zs = [r[0], r[2]]
            .iter()
            .flat_map(|&x| [r[1], r[3]].map(move |y| h0 + gx * x + gy * y))
            .collect::<Vec<_>>();
        let zlo = zs.iter().cloned().fold(f64::INFINITY, f64::min);
        let zhi = zs.iter().cloned().fold(f64::NEG_INFINITY, f64::max) + g.height_m;
        Object {
            shape: Shape::Medium {
                env: Envelope::Layer {
                    rect: r,
                    h0,
                    gx,
                    gy,
                    lo: 0.0,
                    hi: g.height_m,
                },
                extinction: g.g_function * g.leaf_area_density,
            },
            reflectance: refl(s, &g.material),
            kind: ObjectKind::Grass,
            index: i,
            lo: [r[0], r[1], zlo],
            hi: [r[2], r[3], zhi],
        }
    }

    /// Box number `i`: a solid from 50 m below the ground at its centre up to `height_m`
    /// above it.
    fn box_object(&self, s: &WorldScene, i: u32, b: &cfg::BoxObject) -> Object {
        let r = b.rectangle_m;
        let z0 = self.base_of(&r);
        let (lo, hi) = ([r[0], r[1], z0 - 50.0], [r[2], r[3], z0 + b.height_m]);
        Object {
            shape: Shape::Aabb { lo, hi },
            reflectance: refl(s, &b.material),
            kind: ObjectKind::Box,
            index: i,
            lo,
            hi,
        }
    }

    /// Building number `i` onto `objects`: its walls (a solid from 50 m below the ground at
    /// its centre up to the eaves), then its two roof planes rising from the eaves to the
    /// ridge.
    fn push_roof(&self, s: &WorldScene, i: u32, b: &cfg::Roof, objects: &mut Vec<Object>) {
        let r = b.rectangle_m;
        let z0 = self.base_of(&r);
        let (lo, hi) = ([r[0], r[1], z0 - 50.0], [r[2], r[3], z0 + b.eave_height_m]);
        objects.push(Object {
            shape: Shape::Aabb { lo, hi },
            reflectance: refl(s, &b.wall),
            kind: ObjectKind::Wall,
            index: i,
            lo,
            hi,
        });
        let (eave, ridge) = (z0 + b.eave_height_m, z0 + b.ridge_height_m);
        for (rect, h0, gx, gy) in roof_halves(b.ridge, &r, eave, ridge) {
            objects.push(Object {
                shape: Shape::RoofPlane { rect, h0, gx, gy },
                reflectance: refl(s, &b.material),
                kind: ObjectKind::Roof,
                index: i,
                lo: [rect[0], rect[1], eave],
                hi: [rect[2], rect[3], ridge],
            });
        }
    }

    fn index(&mut self, objects: Vec<Object>) {
        if objects.is_empty() {
            self.objects = objects;
            return;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for o in &objects {
            for a in 0..2 {
                lo[a] = lo[a].min(o.lo[a]);
                hi[a] = hi[a].max(o.hi[a]);
            }
            self.top_z = self.top_z.max(o.hi[2]);
        }
        // Cells of 8 m, at most 1024 a side.
        let span = (hi[0] - lo[0]).max(hi[1] - lo[1]);
        self.cell_m = (span / 1024.0).max(8.0);
        self.grid_lo = lo;
        self.grid_n = [
            ((hi[0] - lo[0]) / self.cell_m).floor() as usize + 1,
            ((hi[1] - lo[1]) / self.cell_m).floor() as usize + 1,
        ];
        self.cells = vec![Vec::new(); self.grid_n[0] * self.grid_n[1]];
        for (k, o) in objects.iter().enumerate() {
            let (c0, c1) = (
                self.cell_of(o.lo[0], o.lo[1]),
                self.cell_of(o.hi[0], o.hi[1]),
            );
            for cy in c0[1]..=c1[1] {
                for cx in c0[0]..=c1[0] {
                    self.cells[cy * self.grid_n[0] + cx].push(k as u32);
                }
            }
        }
        self.objects = objects;
    }

    fn cell_of(&self, x: f64, y: f64) -> [usize; 2] {
        let c = |v: f64, a: usize| {
            (((v - self.grid_lo[a]) / self.cell_m).floor().max(0.0) as usize)
                .min(self.grid_n[a] - 1)
        };
        [c(x, 0), c(y, 1)]
    }

    /// The terrain's height at (`x`, `y`), metres (`None` outside a DEM).
    pub fn ground_height(&self, x: f64, y: f64) -> Option<f64> {
        match &self.ground {
            Ground::Plane { h0, gx, gy } => Some(h0 + gx * x + gy * y),
            Ground::Dem {
                dem, cx, cy, datum, ..
            } => dem.height_at(x + cx, y + cy).map(|z| z - datum),
        }
    }

    /// Range along the ray to the terrain, its unit normal there, or `None` when it misses.
    pub fn ground_hit(&self, o: V3, d: V3) -> Option<(f64, V3)> {
        match &self.ground {
            Ground::Plane { h0, gx, gy } => {
                // o.z + s d.z = h0 + gx (o.x + s d.x) + gy (o.y + s d.y)
                let den = d[2] - gx * d[0] - gy * d[1];
                let s = (h0 + gx * o[0] + gy * o[1] - o[2]) / den;
                (s > 0.0 && s.is_finite()).then(|| (s, normalize([-gx, -gy, 1.0])))
            }
            Ground::Dem { min, max, step, .. } => {
                if d[2] >= 0.0 {
                    return None;
                }
                // March from where the ray is at the DEM's top to where it is at its bottom.
                let s0 = ((max + 0.01 - o[2]) / d[2]).max(0.0);
                let s1 = (min - 0.01 - o[2]) / d[2];
                let above = |s: f64| -> Option<bool> {
                    let p = add(o, s, d);
                    self.ground_height(p[0], p[1]).map(|z| p[2] > z)
                };
                let mut a = s0;
                let mut prev = above(a)?;
                let ds = step / d[2].abs().max(0.05);
                while a < s1 {
                    let b = (a + ds).min(s1);
                    let now = above(b)?;
                    if prev && !now {
                        let (mut lo, mut hi) = (a, b);
                        for _ in 0..40 {
                            let m = 0.5 * (lo + hi);
                            if above(m)? { lo = m } else { hi = m }
                        }
                        let s = 0.5 * (lo + hi);
                        let p = add(o, s, d);
                        let e = 0.25;
                        let zx = self.ground_height(p[0] + e, p[1])?
                            - self.ground_height(p[0] - e, p[1])?;
                        let zy = self.ground_height(p[0], p[1] + e)?
                            - self.ground_height(p[0], p[1] - e)?;
                        return Some((s, normalize([-zx / (2.0 * e), -zy / (2.0 * e), 1.0])));
                    }
                    prev = now;
                    a = b;
                }
                None
            }
        }
    }

    /// Traces one ray from `o` along unit `d`: `scratch.hits` gets the first solid hit (the
    /// terrain or an object; none when the ray misses everything) and `scratch.media` the
    /// media crossed before it, sorted by entry range.
    pub fn trace(&self, o: V3, d: V3, scratch: &mut TraceScratch) {
        scratch.hits.clear();
        scratch.media.clear();
        let mut best = self.ground_hit(o, d).map(|(s, n)| Hit {
            range_m: s,
            reflectance: self.ground_reflectance,
            cos_incidence: dot(n, d).abs(),
            kind: ObjectKind::Terrain,
            object: 0,
        });
        if !self.objects.is_empty() && d[2] < 0.0 {
            if scratch.stamp.len() != self.objects.len() {
                scratch.stamp = vec![0; self.objects.len()];
                scratch.ray = 0;
            }
            scratch.ray = scratch.ray.wrapping_add(1);
            if scratch.ray == 0 {
                scratch.stamp.fill(0);
                scratch.ray = 1;
            }
            // The ray's horizontal path between the top of the objects and the lowest ground.
            let zlo = match &self.ground {
                Ground::Plane { .. } => best.map(|h| o[2] + h.range_m * d[2] - 1.0).unwrap_or(-1e4),
                Ground::Dem { min, .. } => min - 1.0,
            };
            let sa = ((self.top_z - o[2]) / d[2]).max(0.0);
            let sb = ((zlo - o[2]) / d[2]).max(sa);
            let (pa, pb) = (add(o, sa, d), add(o, sb, d));
            let n =
                (((pb[0] - pa[0]).abs().max((pb[1] - pa[1]).abs()) / (0.5 * self.cell_m)).ceil()
                    as usize)
                    .clamp(1, 4096);
            let mut last = [usize::MAX; 2];
            for k in 0..=n {
                let f = k as f64 / n as f64;
                let c = self.cell_of(pa[0] + f * (pb[0] - pa[0]), pa[1] + f * (pb[1] - pa[1]));
                if c == last {
                    continue;
                }
                last = c;
                for &id in &self.cells[c[1] * self.grid_n[0] + c[0]] {
                    let slot = &mut scratch.stamp[id as usize];
                    if *slot == scratch.ray {
                        continue;
                    }
                    *slot = scratch.ray;
                    let obj = &self.objects[id as usize];
                    match &obj.shape {
                        Shape::Medium { env, extinction } => {
                            if let Some((a, b)) = env.interval(o, d) {
                                scratch.media.push(MediumSpan {
                                    enter_m: a,
                                    exit_m: b,
                                    extinction_per_m: *extinction,
                                    reflectance: obj.reflectance,
                                    kind: obj.kind,
                                    object: obj.index,
                                });
                            }
                        }
                        shape => {
                            if let Some((s, nrm)) = solid_hit(shape, o, d)
                                && best.is_none_or(|b| s < b.range_m)
                            {
                                best = Some(Hit {
                                    range_m: s,
                                    reflectance: obj.reflectance,
                                    cos_incidence: dot(nrm, d).abs(),
                                    kind: obj.kind,
                                    object: obj.index,
                                });
                            }
                        }
                    }
                }
            }
        }
        if let Some(b) = best {
            scratch.hits.push(b);
            let stop = b.range_m;
            scratch.media.retain_mut(|m| {
                m.exit_m = m.exit_m.min(stop);
                m.exit_m > m.enter_m
            });
        }
        scratch
            .media
            .sort_by(|a, b| a.enter_m.total_cmp(&b.enter_m));
    }
}

/// Reflectance of material `name` in scene `s` (0 when unknown).
fn refl(s: &WorldScene, name: &str) -> f64 {
    s.reflectance(name).unwrap_or(0.0)
}

/// The scene's terrain as traced, and its reflectance.
fn ground_of(s: &WorldScene, base_dir: &Path) -> Result<(Ground, f64), SceneError> {
    Ok(match &s.terrain {
        cfg::Terrain::Flat { height_m, material } => (
            Ground::Plane {
                h0: *height_m,
                gx: 0.0,
                gy: 0.0,
            },
            refl(s, material),
        ),
        cfg::Terrain::Plane {
            height_m,
            slope_deg,
            aspect_deg,
            material,
        } => {
            // Downhill towards the aspect: the height falls by tan(slope) per metre along
            // (sin a, cos a).
            let t = slope_deg.to_radians().tan();
            let a = aspect_deg.to_radians();
            (
                Ground::Plane {
                    h0: *height_m,
                    gx: -t * a.sin(),
                    gy: -t * a.cos(),
                },
                refl(s, material),
            )
        }
        cfg::Terrain::Geotiff {
            path,
            datum_m,
            material,
        } => (
            dem_ground(&base_dir.join(path), *datum_m)?,
            refl(s, material),
        ),
    })
}

/// The terrain from the DEM at `full` (a GeoTIFF), centred on the scene's origin, its heights
/// less `datum_m` (metres); with its lowest and highest heights and the ray march's step
/// (half the smaller pixel side), metres.
fn dem_ground(full: &Path, datum_m: f64) -> Result<Ground, SceneError> {
    let dem = Dem::open(full).map_err(|e| SceneError::Invalid {
        field: "terrain.path",
        reason: e.to_string(),
    })?;
    let (w, h) = (dem.size.0 as f64, dem.size.1 as f64);
    let cx = dem.first_centre[0] + (w - 1.0) / 2.0 * dem.pixel[0];
    let cy = dem.first_centre[1] - (h - 1.0) / 2.0 * dem.pixel[1];
    let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
    for r in 0..dem.size.1 {
        for c in 0..dem.size.0 {
            let x = dem.first_centre[0] + c as f64 * dem.pixel[0];
            let y = dem.first_centre[1] - r as f64 * dem.pixel[1];
            if let Some(z) = dem.height_at(x, y) {
                min = min.min(z - datum_m);
                max = max.max(z - datum_m);
            }
        }
    }
    if !min.is_finite() {
        return Err(SceneError::Invalid {
            field: "terrain.path",
            reason: format!("{}: the DEM has no valid height", full.display()),
        });
    }
    let step = dem.pixel[0].abs().min(dem.pixel[1].abs()) / 2.0;
    Ok(Ground::Dem {
        dem: Box::new(dem),
        cx,
        cy,
        datum: datum_m,
        min,
        max,
        step,
    })
}

/// The envelope of a crown of `shape` centred on `c` (east, north, m), from height `base` to
/// `top` (m), of radius `r` (m).
fn crown_envelope(shape: CrownShape, c: [f64; 2], base: f64, top: f64, r: f64) -> Envelope {
    let [x, y] = c;
    match shape {
        CrownShape::Ellipsoid => Envelope::Ellipsoid {
            c: [x, y, (base + top) / 2.0],
            r,
            rz: (top - base) / 2.0,
        },
        CrownShape::Cone => Envelope::Cone {
            c: [x, y],
            base,
            top,
            r,
        },
        CrownShape::Cylinder => Envelope::Cylinder {
            c: [x, y],
            base,
            top,
            r,
        },
    }
}

/// The two planes of a gable roof over `r` (`[west, south, east, north]`, m) with its ridge
/// along `ridge` through the middle: each half's rectangle and plane `z = h0 + gx x + gy y`,
/// rising from `eave` at the edge to `ridge_z` at the middle (m).
fn roof_halves(
    ridge: Ridge,
    r: &[f64; 4],
    eave: f64,
    ridge_z: f64,
) -> [([f64; 4], f64, f64, f64); 2] {
    match ridge {
        Ridge::EastWest => {
            let m = (r[1] + r[3]) / 2.0;
            let g = (ridge_z - eave) / (m - r[1]);
            // South half rises northwards, north half falls.
            [
                ([r[0], r[1], r[2], m], eave - g * r[1], 0.0, g),
                ([r[0], m, r[2], r[3]], eave + g * r[3], 0.0, -g),
            ]
        }
        Ridge::NorthSouth => {
            let m = (r[0] + r[2]) / 2.0;
            let g = (ridge_z - eave) / (m - r[0]);
            [
                ([r[0], r[1], m, r[3]], eave - g * r[0], g, 0.0),
                ([m, r[1], r[2], r[3]], eave + g * r[2], -g, 0.0),
            ]
        }
    }
}

fn cylinder(p0: V3, axis: V3, len: f64, r: f64, refl: f64, kind: ObjectKind, index: u32) -> Object {
    let p1 = add(p0, len, axis);
    Object {
        shape: Shape::Cylinder { p0, axis, len, r },
        reflectance: refl,
        kind,
        index,
        lo: [
            p0[0].min(p1[0]) - r,
            p0[1].min(p1[1]) - r,
            p0[2].min(p1[2]) - r,
        ],
        hi: [
            p0[0].max(p1[0]) + r,
            p0[1].max(p1[1]) + r,
            p0[2].max(p1[2]) + r,
        ],
    }
}

/// Horizontal radius of a crown envelope at height `h` above the terrain (0 outside).
fn crown_radius_at(c: &cfg::Crown, height: f64, h: f64) -> f64 {
    if h < c.base_m || h > height {
        return 0.0;
    }
    let f = (h - c.base_m) / (height - c.base_m);
    match c.shape {
        CrownShape::Cylinder => c.radius_m,
        CrownShape::Cone => c.radius_m * (1.0 - f),
        CrownShape::Ellipsoid => c.radius_m * (1.0 - (2.0 * f - 1.0).powi(2)).max(0.0).sqrt(),
    }
}

/// Roots of `a s² + b s + c = 0` (none, or two, the smaller first).
fn quadratic(a: f64, b: f64, c: f64) -> Option<(f64, f64)> {
    if a.abs() < 1e-300 {
        if b.abs() < 1e-300 {
            return None;
        }
        let s = -c / b;
        return Some((s, s));
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return None;
    }
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    let (r1, r2) = (q / a, if q != 0.0 { c / q } else { -b / a - q / a });
    Some((r1.min(r2), r1.max(r2)))
}

/// Range interval `[enter, exit]` of the ray inside the slab `lo ≤ o_a + s d_a ≤ hi`.
fn slab(o: f64, d: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
    if d.abs() < 1e-300 {
        return (o >= lo && o <= hi).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let (a, b) = ((lo - o) / d, (hi - o) / d);
    Some((a.min(b), a.max(b)))
}

fn intersect(a: (f64, f64), b: (f64, f64)) -> Option<(f64, f64)> {
    let r = (a.0.max(b.0), a.1.min(b.1));
    (r.0 < r.1).then_some(r)
}

impl Envelope {
    /// The ray's range interval inside the envelope (clipped to ranges > 0).
    fn interval(&self, o: V3, d: V3) -> Option<(f64, f64)> {
        let iv = match *self {
            Envelope::Ellipsoid { c, r, rz } => {
                let w = sub(o, c);
                let (wz, dz) = (w[2] * r / rz, d[2] * r / rz);
                let a = d[0] * d[0] + d[1] * d[1] + dz * dz;
                let b = 2.0 * (w[0] * d[0] + w[1] * d[1] + wz * dz);
                let cc = w[0] * w[0] + w[1] * w[1] + wz * wz - r * r;
                quadratic(a, b, cc)?
            }
            Envelope::Cylinder { c, base, top, r } => {
                let (wx, wy) = (o[0] - c[0], o[1] - c[1]);
                let a = d[0] * d[0] + d[1] * d[1];
                let side = if a < 1e-300 {
                    (wx * wx + wy * wy <= r * r).then_some((f64::NEG_INFINITY, f64::INFINITY))?
                } else {
                    quadratic(a, 2.0 * (wx * d[0] + wy * d[1]), wx * wx + wy * wy - r * r)?
                };
                intersect(side, slab(o[2], d[2], base, top)?)?
            }
            Envelope::Cone { c, base, top, r } => {
                // Inside: horizontal distance <= k (top − z), base <= z <= top.
                let k = r / (top - base);
                let (wx, wy, u0) = (o[0] - c[0], o[1] - c[1], top - o[2]);
                let a = d[0] * d[0] + d[1] * d[1] - k * k * d[2] * d[2];
                let b = 2.0 * (wx * d[0] + wy * d[1] + k * k * u0 * d[2]);
                let cc = wx * wx + wy * wy - k * k * u0 * u0;
                let z = slab(o[2], d[2], base, top)?;
                let inside = |s: f64| {
                    let p = add(o, s, d);
                    let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                    (dx * dx + dy * dy).sqrt() <= k * (top - p[2]) + 1e-12
                };
                let mut cand = [z.0, z.1, f64::NAN, f64::NAN];
                if let Some((r1, r2)) = quadratic(a, b, cc) {
                    cand[2] = r1.clamp(z.0, z.1);
                    cand[3] = r2.clamp(z.0, z.1);
                }
                // Boundary candidates (a missing root repeats the slab's entry).
                let mut pts = cand.map(|v| if v.is_finite() { v } else { z.0 });
                pts.sort_by(f64::total_cmp);
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for w in pts.windows(2) {
                    if w[1] > w[0] && inside(0.5 * (w[0] + w[1])) {
                        lo = lo.min(w[0]);
                        hi = hi.max(w[1]);
                    }
                }
                (lo < hi).then_some((lo, hi))?
            }
            Envelope::Layer {
                rect,
                h0,
                gx,
                gy,
                lo,
                hi,
            } => {
                // Height above the ground plane along the ray is linear in s.
                let q0 = o[2] - (h0 + gx * o[0] + gy * o[1]);
                let q1 = d[2] - gx * d[0] - gy * d[1];
                let h = slab(q0, q1, lo, hi)?;
                let x = slab(o[0], d[0], rect[0], rect[2])?;
                let y = slab(o[1], d[1], rect[1], rect[3])?;
                intersect(intersect(h, x)?, y)?
            }
        };
        let iv = (iv.0.max(0.0), iv.1);
        (iv.0 < iv.1).then_some(iv)
    }
}

/// First hit of the ray on a solid shape: range and unit normal.
fn solid_hit(shape: &Shape, o: V3, d: V3) -> Option<(f64, V3)> {
    match *shape {
        Shape::Cylinder { p0, axis, len, r } => {
            let w = sub(o, p0);
            let (wa, da) = (dot(w, axis), dot(d, axis));
            let wp = add(w, -wa, axis);
            let dp = add(d, -da, axis);
            let (s1, s2) = quadratic(dot(dp, dp), 2.0 * dot(wp, dp), dot(wp, wp) - r * r)?;
            for s in [s1, s2] {
                let t = wa + s * da;
                if s > 0.0 && (0.0..=len).contains(&t) {
                    let radial = add(add(w, s, d), -t, axis);
                    return Some((s, normalize(radial)));
                }
            }
            None
        }
        Shape::Aabb { lo, hi } => {
            let mut iv = (0.0f64, f64::INFINITY);
            let mut axis = usize::MAX;
            for a in 0..3 {
                let (e, x) = slab(o[a], d[a], lo[a], hi[a])?;
                if e > iv.0 {
                    iv.0 = e;
                    axis = a;
                }
                iv.1 = iv.1.min(x);
            }
            if iv.0 >= iv.1 || axis == usize::MAX {
                return None;
            }
            let mut n = [0.0; 3];
            n[axis] = -d[axis].signum();
            Some((iv.0, n))
        }
        Shape::RoofPlane { rect, h0, gx, gy } => {
            let den = d[2] - gx * d[0] - gy * d[1];
            let s = (h0 + gx * o[0] + gy * o[1] - o[2]) / den;
            let p = add(o, s, d);
            (s > 0.0
                && s.is_finite()
                && p[0] >= rect[0]
                && p[0] <= rect[2]
                && p[1] >= rect[1]
                && p[1] <= rect[3])
                .then(|| (s, normalize([-gx, -gy, 1.0])))
        }
        Shape::Medium { .. } => None,
    }
}

#[cfg(test)]
mod tests;
