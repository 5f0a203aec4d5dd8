//! Previews: a rendered conformed mesh shows an object of plausible size, shaded (not a
//! flat silhouette), in the colours asked for; the CLI writes a PNG that decodes.

use crate::common;
use common::{CHILD_LIMIT, Deadline};

use conformd::render::{Colouring, RenderOptions, View, colour_map, render};
use conformd::template::{self as templates, Kind};

fn coverage(img: &image::RgbImage, bg: [u8; 3]) -> (f64, f64) {
    let px: Vec<&image::Rgb<u8>> = img.pixels().filter(|p| p.0 != bg).collect();
    let share = px.len() as f64 / (img.width() * img.height()) as f64;
    let lum: Vec<f64> = px
        .iter()
        .map(|p| p.0.iter().map(|&c| c as f64).sum::<f64>() / 3.0)
        .collect();
    let mean = lum.iter().sum::<f64>() / lum.len().max(1) as f64;
    let sd = (lum.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / lum.len().max(1) as f64).sqrt();
    (share, sd)
}

#[test]
fn preview_shows_a_shaded_object() {
    let fig = templates::build(Kind::Pig, 3000);
    let opts = RenderOptions {
        width: 800,
        height: 600,
        views: vec![View::named("side").unwrap()],
        ..Default::default()
    };
    let img = render(&fig.mesh, &Colouring::Plain, &opts);
    let (share, sd) = coverage(&img, opts.background);
    eprintln!(
        "side view: object covers {:.1}% of the image, brightness sd {sd:.1}",
        share * 100.0
    );
    assert!(
        (0.08..0.7).contains(&share),
        "object covers {:.1}%",
        share * 100.0
    );
    assert!(sd > 8.0, "shaded, not flat: brightness sd {sd:.1}");

    // colouring by values: the colour bar's extremes appear
    let values: Vec<f64> = fig.mesh.vertices.iter().map(|p| p.x).collect();
    let (min, max) = (
        values.iter().cloned().fold(f64::INFINITY, f64::min),
        values.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    );
    let img = render(
        &fig.mesh,
        &Colouring::Values {
            values,
            min,
            max,
            unit: "X".into(),
        },
        &opts,
    );
    let has = |c: [u8; 3]| img.pixels().any(|p| p.0 == c);
    assert!(
        has(colour_map(0.0)) && has(colour_map(1.0)),
        "colour bar drawn"
    );
}

#[test]
fn cli_renders_a_png_and_colours_by_distance() {
    let dir = tempfile::tempdir().unwrap();
    let fig = templates::build(Kind::Body, 2500);
    conformd::mesh::write_mesh(&dir.path().join("body.obj"), &fig.mesh).unwrap();
    // the scan: only the body above the hips, so the legs lie far from it
    let upper: Vec<_> = fig
        .mesh
        .vertices
        .iter()
        .filter(|p| p.z > 0.95)
        .map(|p| p + conformd::mesh::V3::new(0.01, 0.0, 0.0))
        .collect();
    let scan = conformd::mesh::Mesh::new(upper, vec![]);
    conformd::mesh::write_mesh(&dir.path().join("scan.ply"), &scan).unwrap();
    let bin = env!("CARGO_BIN_EXE_conformd");
    common::succeeded(
        std::process::Command::new(bin)
            .args([
                "render",
                "body.obj",
                "--colour-by",
                "distance-to=scan.ply",
                "--views",
                "front,top",
                "--out",
                "b.png",
            ])
            .current_dir(dir.path())
            .output_within(CHILD_LIMIT),
    );
    let img = image::open(dir.path().join("b.png")).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (800, 600));
    let (share, _) = coverage(&img, [250, 250, 250]);
    assert!(share > 0.03, "{share}");
    // far vertices get the far colour: in the front view (the left panel), the legs are
    // yellow-green (green well over blue), the chest purple-blue (blue over green)
    let panel = (800 - 90) / 2;
    let body: Vec<(u32, [u8; 3])> = img
        .enumerate_pixels()
        .filter(|(x, _, p)| *x < panel && p.0 != [250, 250, 250])
        .map(|(_, y, p)| (y, p.0))
        .collect();
    let (top, bottom) = body
        .iter()
        .fold((u32::MAX, 0), |(a, b), (y, _)| (a.min(*y), b.max(*y)));
    let green_over_blue = |from: f64, to: f64| {
        let rows = |f: f64| top + ((bottom - top) as f64 * f) as u32;
        let band: Vec<f64> = body
            .iter()
            .filter(|(y, _)| *y >= rows(from) && *y < rows(to))
            .map(|(_, c)| c[1] as f64 - c[2] as f64)
            .collect();
        band.iter().sum::<f64>() / band.len().max(1) as f64
    };
    let (chest, legs) = (green_over_blue(0.15, 0.35), green_over_blue(0.75, 0.95));
    eprintln!("green over blue: legs {legs:.0}, chest {chest:.0}");
    assert!(legs > 40.0 && chest < 0.0, "legs {legs}, chest {chest}");
    let out = std::process::Command::new(bin)
        .args(["render", "body.obj", "--views", "below", "--out", "c.png"])
        .current_dir(dir.path())
        .output_within(CHILD_LIMIT);
    assert!(
        !out.status.success()
            && String::from_utf8_lossy(&out.stderr).contains("unknown view 'below'")
    );
}
