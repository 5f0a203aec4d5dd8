//! A small software rasterizer for previews and plots: shaded, orthographic views of a
//! mesh (z-buffer, per-pixel Lambert shading from interpolated normals), coloured plainly,
//! by vertex group, or by a value per vertex with a colour bar; written as PNG. No GPU and
//! no window, so it runs on a headless station.

mod font;
pub mod plot;
pub mod raster;

use crate::mesh::{Mesh, V3};
use image::{Rgb, RgbImage};
use nalgebra::{Rotation3, Vector3};

/// A view direction: the camera circles the object (azimuth about z from +x towards +y)
/// and looks down by `elevation` degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    pub azimuth: f64,
    pub elevation: f64,
}

impl View {
    /// Named views for a subject facing +x with z up: front, back, left, right, top,
    /// and `three-quarter`.
    pub fn named(name: &str) -> Option<View> {
        let (azimuth, elevation) = match name {
            "front" => (0.0, 10.0),
            "back" => (180.0, 10.0),
            "left" => (90.0, 10.0),
            "right" | "side" => (-90.0, 10.0),
            "top" => (0.0, 89.0),
            "three-quarter" => (-45.0, 25.0),
            _ => return None,
        };
        Some(View { azimuth, elevation })
    }
}

/// How vertices are coloured.
#[derive(Debug, Clone)]
pub enum Colouring {
    Plain,
    /// each named group its own colour (a vertex in several takes the first)
    Groups,
    /// one value per vertex mapped through a colour map over [min, max], with a colour
    /// bar labelled with the range and `unit` (up to two lines, 10 characters each)
    Values {
        values: Vec<f64>,
        min: f64,
        max: f64,
        unit: String,
    },
}

impl Colouring {
    /// Distances (one per vertex) on a colour map from 0 to the largest, the bar
    /// labelled "DISTANCE" over `unit` (e.g. "MM", "MESH UNITS").
    pub fn distances(values: Vec<f64>, unit: &str) -> Colouring {
        let max = values
            .iter()
            .cloned()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        Colouring::Values {
            values,
            min: 0.0,
            max,
            unit: format!("DISTANCE\n{unit}"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct RenderOptions {
    pub width: u32,
    pub height: u32,
    pub views: Vec<View>,
    pub background: [u8; 3],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 800,
            height: 600,
            views: vec![
                View::named("three-quarter").unwrap(),
                View::named("side").unwrap(),
            ],
            background: [250, 250, 250],
        }
    }
}

const PALETTE: [[u8; 3]; 10] = [
    [86, 140, 200],
    [230, 140, 60],
    [90, 175, 90],
    [205, 85, 85],
    [150, 115, 190],
    [150, 110, 90],
    [220, 130, 180],
    [140, 140, 140],
    [190, 190, 70],
    [70, 190, 200],
];

/// A viridis-like map of t in [0, 1].
pub fn colour_map(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    } * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f64;
    std::array::from_fn(|c| (STOPS[i][c] * (1.0 - f) + STOPS[i + 1][c] * f).round() as u8)
}

fn vertex_colours(mesh: &Mesh, colouring: &Colouring) -> Vec<[f64; 3]> {
    let n = mesh.vertices.len();
    let to_f = |c: [u8; 3]| {
        [
            c[0] as f64 / 255.0,
            c[1] as f64 / 255.0,
            c[2] as f64 / 255.0,
        ]
    };
    match colouring {
        Colouring::Plain => vec![to_f([200, 190, 175]); n],
        Colouring::Groups => {
            let mut c = vec![to_f([200, 200, 200]); n];
            let mut done = vec![false; n];
            for (k, (_, vs)) in mesh.groups.iter().enumerate() {
                for &v in vs {
                    if let Some(d) = done.get_mut(v as usize).filter(|d| !**d) {
                        *d = true;
                        c[v as usize] = to_f(PALETTE[k % PALETTE.len()]);
                    }
                }
            }
            c
        }
        Colouring::Values {
            values, min, max, ..
        } => {
            let span = (max - min).abs().max(1e-300);
            (0..n)
                .map(|i| {
                    to_f(colour_map(
                        (values.get(i).copied().unwrap_or(*min) - min) / span,
                    ))
                })
                .collect()
        }
    }
}

/// Renders the mesh's views side by side (and a colour bar when colouring by values).
///
/// - `mesh`: #V vertices, #F triangles (a point cloud draws nothing)
/// - returns a `width` x `height` RGB image
pub fn render(mesh: &Mesh, colouring: &Colouring, opts: &RenderOptions) -> RgbImage {
    let mut img = RgbImage::from_pixel(opts.width.max(1), opts.height.max(1), Rgb(opts.background));
    let bar = matches!(colouring, Colouring::Values { .. });
    let bar_w = if bar { 90.min(opts.width / 4) } else { 0 };
    let views = if opts.views.is_empty() {
        vec![View::named("three-quarter").unwrap()]
    } else {
        opts.views.clone()
    };
    let panel_w = (opts.width - bar_w) / views.len() as u32;
    let colours = vertex_colours(mesh, colouring);
    let normals = mesh.vertex_normals();
    let Some((lo, hi)) = mesh.bounding_box() else {
        return img;
    };
    let centre = (lo + hi) / 2.0;
    let radius = ((hi - lo).norm() / 2.0).max(1e-300);
    for (k, view) in views.iter().enumerate() {
        draw_view(
            &mut img,
            mesh,
            &colours,
            &normals,
            centre,
            radius,
            view,
            k as u32 * panel_w,
            panel_w,
            opts.height,
        );
    }
    if let Colouring::Values { min, max, unit, .. } = colouring {
        draw_colour_bar(
            &mut img,
            opts.width - bar_w,
            bar_w,
            opts.height,
            *min,
            *max,
            unit,
        );
    }
    img
}

#[allow(clippy::too_many_arguments)]
fn draw_view(
    img: &mut RgbImage,
    mesh: &Mesh,
    colours: &[[f64; 3]],
    normals: &[V3],
    centre: V3,
    radius: f64,
    view: &View,
    x0: u32,
    w: u32,
    h: u32,
) {
    // camera frame: rows are screen right, screen up, towards the viewer
    let rot = Rotation3::from_euler_angles(0.0, 0.0, -view.azimuth.to_radians());
    // tilting about y by +elevation brings the top towards a camera on the +x side
    let tilt = Rotation3::from_axis_angle(&Vector3::y_axis(), view.elevation.to_radians());
    let to_cam = |p: &V3| -> V3 {
        let q = tilt * (rot * (p - centre));
        // a camera on +x looking along -x: screen right = +y, up = z, depth = x
        V3::new(q.y, q.z, q.x)
    };
    let scale = 0.92 * (w.min(h) as f64) / (2.0 * radius);
    let (cx, cy) = (x0 as f64 + w as f64 / 2.0, h as f64 / 2.0);
    let screen: Vec<V3> = mesh
        .vertices
        .iter()
        .map(|p| {
            let c = to_cam(p);
            V3::new(cx + c.x * scale, cy - c.y * scale, c.z)
        })
        .collect();
    let cam_normals: Vec<V3> = normals.iter().map(|n| to_cam(&(n + centre))).collect();
    let light = V3::new(-0.4, 0.5, 0.77).normalize();
    // the panel's own pixels; nearer to the viewer is larger z, so the key is -z
    let panel: Vec<V3> = screen
        .iter()
        .map(|p| V3::new(p.x - x0 as f64, p.y, -p.z))
        .collect();
    let frags = raster::rasterize(&panel, &mesh.triangles, w as usize, h as usize, |_| true);
    for (i, f) in frags.iter().enumerate() {
        let Some(f) = f else { continue };
        let [w0, w1, w2] = f.weights();
        let [ia, ib, ic] = mesh.triangles[f.triangle as usize].map(|i| i as usize);
        let n = cam_normals[ia] * w0 + cam_normals[ib] * w1 + cam_normals[ic] * w2;
        let n = n.try_normalize(0.0).unwrap_or(V3::z());
        // two-sided Lambert with a little ambient light
        let shade = 0.25 + 0.75 * n.dot(&light).abs();
        let col: [u8; 3] = std::array::from_fn(|k| {
            let v = colours[ia][k] * w0 + colours[ib][k] * w1 + colours[ic][k] * w2;
            (v * shade * 255.0).round().clamp(0.0, 255.0) as u8
        });
        img.put_pixel(x0 + (i as u32 % w), i as u32 / w, Rgb(col));
    }
}

fn draw_colour_bar(img: &mut RgbImage, x0: u32, w: u32, h: u32, min: f64, max: f64, unit: &str) {
    if w < 20 || h < 60 {
        return;
    }
    // room below the bar for two lines of its label (what, then the unit)
    let (top, bottom) = (30u32, h - 44);
    let (bx0, bx1) = (x0 + 10, x0 + 30.min(w - 4));
    for y in top..bottom {
        // the top row shows the maximum, the bottom row the minimum, exactly
        let t = 1.0 - (y - top) as f64 / (bottom - top - 1) as f64;
        let c = colour_map(t);
        for x in bx0..bx1 {
            img.put_pixel(x, y, Rgb(c));
        }
    }
    let label = |v: f64| {
        if v.abs() >= 1e-2 && v.abs() < 1e4 || v == 0.0 {
            format!("{v:.3}")
        } else {
            format!("{v:.2e}")
        }
    };
    font::draw(img, bx1 + 4, top, &label(max), [30, 30, 30], 2);
    font::draw(img, bx1 + 4, bottom - 10, &label(min), [30, 30, 30], 2);
    for (k, line) in unit.lines().take(2).enumerate() {
        font::draw(img, bx0, bottom + 8 + 16 * k as u32, line, [30, 30, 30], 2);
    }
}

/// An image (grey, 16-bit grey or colour) encoded as PNG in memory.
pub fn png_bytes<P>(img: &image::ImageBuffer<P, Vec<P::Subpixel>>) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .expect("PNG encodes 8- and 16-bit grey and colour buffers in memory");
    bytes
}

/// Writes an image as PNG, atomically.
pub fn save_png<P>(
    img: &image::ImageBuffer<P, Vec<P::Subpixel>>,
    path: &std::path::Path,
) -> Result<(), crate::mesh::FileError>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    crate::files::write_atomic(path, &png_bytes(img))
}

/// Places images in a grid (row-major), each cell the size of the first image; an
/// optional label is drawn at the top left of each cell.
pub fn sheet(cells: &[(RgbImage, String)], columns: usize, background: [u8; 3]) -> RgbImage {
    let Some((first, _)) = cells.first() else {
        return RgbImage::new(1, 1);
    };
    let (cw, ch) = first.dimensions();
    let cols = columns.max(1) as u32;
    let rows = cells.len().div_ceil(columns.max(1)) as u32;
    let mut out = RgbImage::from_pixel(cw * cols, ch * rows, Rgb(background));
    for (k, (img, label)) in cells.iter().enumerate() {
        let (cx, cy) = ((k as u32 % cols) * cw, (k as u32 / cols) * ch);
        image::imageops::overlay(&mut out, img, cx as i64, cy as i64);
        font::draw(&mut out, cx + 6, cy + 6, label, [30, 30, 30], 2);
    }
    out
}
