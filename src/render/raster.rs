//! The z-buffer scan conversion that previews and the virtual rig's cameras share: which
//! triangle each pixel sees, and where in it.

use crate::mesh::V3;

/// What one pixel sees: a triangle, the pixel centre's barycentric weights of its first
/// two corners (the third is the rest), and the depth key that won the z-test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fragment {
    pub triangle: u32,
    pub bary: [f32; 2],
    pub key: f32,
}

impl Fragment {
    const EMPTY: Fragment = Fragment {
        triangle: u32::MAX,
        bary: [0.0; 2],
        key: f32::INFINITY,
    };

    /// The three barycentric weights.
    pub fn weights(&self) -> [f64; 3] {
        let [a, b] = self.bary.map(f64::from);
        [a, b, 1.0 - a - b]
    }
}

/// Scan-converts triangles into a `width` x `height` buffer (row-major).
///
/// In: `screen` (#V): each vertex's pixel coordinates x, y (pixel (i, j) covers
/// [i, i+1) x [j, j+1), sampled at its centre) and a depth key that is linear in screen
/// space (orthographic depth, or -1/z for a perspective camera); the smaller key is
/// nearer. `triangles` (#F) index into `screen`; `keep(t)` leaves triangle t out when
/// false (behind a camera, culled).
/// Out: one entry per pixel: `Some(fragment)` of the nearest triangle covering it.
pub fn rasterize(
    screen: &[V3],
    triangles: &[[u32; 3]],
    width: usize,
    height: usize,
    keep: impl Fn(usize) -> bool,
) -> Vec<Option<Fragment>> {
    let mut buf = vec![Fragment::EMPTY; width * height];
    if width == 0 || height == 0 {
        return vec![];
    }
    for (ti, t) in triangles.iter().enumerate() {
        if !keep(ti) {
            continue;
        }
        let [a, b, c] = t.map(|i| screen[i as usize]);
        let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
        if !(area.abs() >= 1e-12) {
            continue;
        }
        let x0 = a.x.min(b.x).min(c.x).floor().max(0.0) as usize;
        let x1 = (a.x.max(b.x).max(c.x).ceil().max(0.0) as usize).min(width - 1);
        let y0 = a.y.min(b.y).min(c.y).floor().max(0.0) as usize;
        let y1 = (a.y.max(b.y).max(c.y).ceil().max(0.0) as usize).min(height - 1);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (fx, fy) = (x as f64 + 0.5, y as f64 + 0.5);
                let w0 = ((b.x - fx) * (c.y - fy) - (b.y - fy) * (c.x - fx)) / area;
                let w1 = ((c.x - fx) * (a.y - fy) - (c.y - fy) * (a.x - fx)) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let key = (a.z * w0 + b.z * w1 + c.z * w2) as f32;
                let f = &mut buf[y * width + x];
                if key < f.key {
                    *f = Fragment {
                        triangle: ti as u32,
                        bary: [w0 as f32, w1 as f32],
                        key,
                    };
                }
            }
        }
    }
    buf.into_iter()
        .map(|f| (f.triangle != u32::MAX).then_some(f))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearer_triangle_wins_and_weights_interpolate() {
        // two overlapping triangles; the second is nearer (smaller key)
        let screen = vec![
            V3::new(0.0, 0.0, 5.0),
            V3::new(10.0, 0.0, 5.0),
            V3::new(0.0, 10.0, 5.0),
            V3::new(0.0, 0.0, 1.0),
            V3::new(10.0, 0.0, 1.0),
            V3::new(0.0, 10.0, 1.0),
        ];
        let tris = [[0, 1, 2], [3, 4, 5]];
        let buf = rasterize(&screen, &tris, 10, 10, |_| true);
        let f = buf[2 * 10 + 2].unwrap();
        assert_eq!(f.triangle, 1);
        let w = f.weights();
        // pixel (2, 2) is sampled at (2.5, 2.5)
        assert!((w[1] - 0.25).abs() < 1e-6 && (w[2] - 0.25).abs() < 1e-6);
        assert!(buf[9 * 10 + 9].is_none(), "outside both");
        let only_first = rasterize(&screen, &tris, 10, 10, |t| t == 0);
        assert_eq!(only_first[22].unwrap().triangle, 0);
    }
}
