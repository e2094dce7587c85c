use super::*;

fn scene(text: &str) -> Scene {
    let mut full = String::from(text);
    full.push_str(
        "\n[flight]\nlines = [{ start_m = [0.0, 0.0], end_m = [1.0, 0.0] }]\n\
         [sensor]\nprofile = \"x.toml\"\n",
    );
    let s: WorldScene = crate::sim::analytic_scene::parse_toml(&full, "t").unwrap();
    Scene::build(&s, Path::new(".")).unwrap()
}

fn trace(sc: &Scene, o: V3, d: V3) -> TraceScratch {
    let mut t = TraceScratch::default();
    sc.trace(o, normalize(d), &mut t);
    t
}

#[test]
fn terrain_planes_are_hit_where_they_are() {
    let sc =
        scene("[terrain]\nkind = \"plane\"\nheight_m = 5.0\nslope_deg = 45.0\naspect_deg = 90.0");
    // Falls eastwards: 1 m per metre east.
    assert!((sc.ground_height(3.0, 7.0).unwrap() - 2.0).abs() < 1e-12);
    let t = trace(&sc, [3.0, 0.0, 100.0], [0.0, 0.0, -1.0]);
    assert!((t.hits[0].range_m - 98.0).abs() < 1e-9);
    assert!((t.hits[0].cos_incidence - 45f64.to_radians().cos()).abs() < 1e-12);
    // A ray going up misses.
    assert!(
        trace(&sc, [0.0, 0.0, 100.0], [0.0, 0.0, 1.0])
            .hits
            .is_empty()
    );
}

#[test]
fn stems_branches_boxes_and_roofs_stop_the_ray_at_their_surface() {
    let sc = scene(
        "[[tree]]\nposition_m = [0.0, 0.0]\nheight_m = 10.0\nstem_radius_m = 0.5\n\
         crown = { base_m = 5.0, radius_m = 2.0 }\n\
         branches = [{ height_m = 6.0, azimuth_deg = 90.0, zenith_deg = 90.0, length_m = 3.0, radius_m = 0.1 }]\n\
         [[box]]\nrectangle_m = [10.0, 10.0, 14.0, 12.0]\nheight_m = 4.0\n\
         [[roof]]\nrectangle_m = [20.0, 0.0, 30.0, 10.0]\neave_height_m = 3.0\nridge_height_m = 5.0",
    );
    // Down the stem's axis: its top is open (no cap), the ray meets the ground inside it...
    // so aim at the stem's side from the west, horizontally at 2 m.
    let t = trace(&sc, [-10.0, 0.0, 2.0], [1.0, 0.0, -1e-9]);
    assert_eq!(t.hits[0].kind, ObjectKind::Stem);
    assert!((t.hits[0].range_m - 9.5).abs() < 1e-6);
    assert!((t.hits[0].cos_incidence - 1.0).abs() < 1e-6);
    // The branch runs east at 6 m: a vertical ray at x = 2 meets its top at 6.1 m.
    let t = trace(&sc, [2.0, 0.0, 50.0], [0.0, 0.0, -1.0]);
    assert_eq!(t.hits[0].kind, ObjectKind::Branch);
    assert!((t.hits[0].range_m - (50.0 - 6.1)).abs() < 1e-6);
    let t = trace(&sc, [12.0, 11.0, 50.0], [0.0, 0.0, -1.0]);
    assert_eq!(t.hits[0].kind, ObjectKind::Box);
    assert!((t.hits[0].range_m - 46.0).abs() < 1e-9);
    // The gable roof: ridge east-west at y = 5 (5 m), eaves at y = 0 and 10 (3 m).
    let t = trace(&sc, [25.0, 2.5, 50.0], [0.0, 0.0, -1.0]);
    assert_eq!(t.hits[0].kind, ObjectKind::Roof);
    assert!((t.hits[0].range_m - 46.0).abs() < 1e-9);
    let slope = (2.0f64 / 5.0).atan();
    assert!((t.hits[0].cos_incidence - slope.cos()).abs() < 1e-12);
    // A wall, from the side.
    let t = trace(&sc, [40.0, 5.0, 1.0], [-1.0, 0.0, -1e-9]);
    assert_eq!(t.hits[0].kind, ObjectKind::Wall);
    assert!((t.hits[0].range_m - 10.0).abs() < 1e-6);
}

#[test]
fn crown_envelopes_give_the_chord_the_ray_crosses() {
    for (shape, want) in [
        // Vertical ray 1 m from the axis of a crown 4..10 m, radius 2.
        ("ellipsoid", 6.0 * (1.0f64 - 0.25).sqrt()),
        ("cylinder", 6.0),
        // Cone radius 2 at 4 m to 0 at 10 m: radius 1 at 7 m, so 4..7 m.
        ("cone", 3.0),
    ] {
        let sc = scene(&format!(
            "[[tree]]\nposition_m = [0.0, 0.0]\nheight_m = 10.0\nstem_radius_m = 0.0\n\
             leaf_area_density = 1.0\ncrown = {{ shape = \"{shape}\", base_m = 4.0, radius_m = 2.0 }}"
        ));
        let t = trace(&sc, [1.0, 0.0, 100.0], [0.0, 0.0, -1.0]);
        assert_eq!(t.media.len(), 1, "{shape}");
        let m = t.media[0];
        assert!(
            ((m.exit_m - m.enter_m) - want).abs() < 1e-9,
            "{shape}: {m:?}"
        );
        assert!((m.extinction_per_m - 0.5).abs() < 1e-12);
        // A slanted ray through a cone: the chord's ends are on the envelope.
        let t = trace(&sc, [-30.0, 0.2, 30.0], [1.0, 0.0, -0.8]);
        if let Some(m) = t.media.first() {
            for s in [m.enter_m, m.exit_m] {
                let p = [-30.0 + s * 0.780_868_809, 0.2, 30.0 - s * 0.624_695_047];
                let r = (p[0] * p[0] + p[1] * p[1]).sqrt();
                let z = p[2];
                let on = match shape {
                    "ellipsoid" => {
                        ((r / 2.0).powi(2) + ((z - 7.0) / 3.0).powi(2) - 1.0).abs() < 1e-6
                    }
                    "cylinder" => {
                        (r - 2.0).abs() < 1e-6 || (z - 4.0).abs() < 1e-6 || (z - 10.0).abs() < 1e-6
                    }
                    _ => (r - 2.0 * (10.0 - z) / 6.0).abs() < 1e-6 || (z - 4.0).abs() < 1e-6,
                };
                assert!(on, "{shape}: r {r} z {z}");
            }
        }
    }
}

#[test]
fn media_stop_at_the_first_solid_and_grass_follows_the_terrain() {
    let sc = scene(
        "[terrain]\nkind = \"plane\"\nslope_deg = 10.0\naspect_deg = 0.0\n\
         [[grass]]\nrectangle_m = [-5.0, -5.0, 5.0, 5.0]\nheight_m = 0.8\nleaf_area_density = 2.0",
    );
    let t = trace(&sc, [1.0, 2.0, 100.0], [0.0, 0.0, -1.0]);
    let g = sc.ground_height(1.0, 2.0).unwrap();
    assert_eq!(t.media.len(), 1);
    assert!((t.media[0].enter_m - (100.0 - g - 0.8)).abs() < 1e-9);
    assert!((t.media[0].exit_m - (100.0 - g)).abs() < 1e-9);
    assert!((t.hits[0].range_m - (100.0 - g)).abs() < 1e-9);
    // Outside the patch: bare ground.
    assert!(
        trace(&sc, [7.0, 0.0, 100.0], [0.0, 0.0, -1.0])
            .media
            .is_empty()
    );
}

#[test]
fn many_objects_are_found_through_the_grid() {
    let mut text = String::new();
    for i in 0..40 {
        for j in 0..40 {
            text.push_str(&format!(
                "[[box]]\nrectangle_m = [{x}, {y}, {x1}, {y1}]\nheight_m = {h}\n",
                x = i as f64 * 10.0,
                y = j as f64 * 10.0,
                x1 = i as f64 * 10.0 + 2.0,
                y1 = j as f64 * 10.0 + 2.0,
                h = 1.0 + (i + j) as f64 * 0.1
            ));
        }
    }
    let sc = scene(&text);
    for (i, j) in [(0, 0), (17, 3), (39, 39)] {
        let t = trace(
            &sc,
            [i as f64 * 10.0 + 1.0, j as f64 * 10.0 + 1.0, 500.0],
            [0.0, 0.0, -1.0],
        );
        assert_eq!(t.hits[0].kind, ObjectKind::Box);
        assert!((t.hits[0].range_m - (500.0 - 1.0 - (i + j) as f64 * 0.1)).abs() < 1e-9);
    }
    let t = trace(&sc, [5.0, 5.0, 500.0], [0.0, 0.0, -1.0]);
    assert_eq!(t.hits[0].kind, ObjectKind::Terrain);
}
