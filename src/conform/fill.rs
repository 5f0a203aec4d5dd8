//! Missing-data filling, the "grass fire" of Ju et al. 2004, section 2.3: vertices without
//! a match take the mean displacement of their matched neighbours, spreading inward from
//! the border of each hole one ring at a time, until every reachable vertex has one.

use crate::mesh::V3;

/// Fills `disp` for unmatched vertices, in place.
///
/// - `neighbours`: #V neighbour lists; `matched`: #V labels (TRUE = has a match)
/// - `disp`: #V displacements; read for matched vertices, written for the others
/// - returns #V ring numbers: 0 for matched vertices, k for vertices filled in the k-th
///   ring from a hole's border, `u32::MAX` for vertices no match can reach (their
///   displacement is left at zero)
///
/// Deterministic: each ring is computed from the previous rings only, never from
/// vertices filled in the same ring, so the result does not depend on vertex order.
pub fn grass_fire(neighbours: &[Vec<u32>], matched: &[bool], disp: &mut [V3]) -> Vec<u32> {
    let n = matched.len();
    let mut ring: Vec<u32> = matched
        .iter()
        .map(|&m| if m { 0 } else { u32::MAX })
        .collect();
    let mut frontier: Vec<usize> = (0..n)
        .filter(|&i| !matched[i] && neighbours[i].iter().any(|&j| matched[j as usize]))
        .collect();
    for v in (0..n).filter(|&i| !matched[i]) {
        disp[v] = V3::zeros();
    }
    let mut k = 0;
    while !frontier.is_empty() {
        k += 1;
        let updates: Vec<(usize, V3)> = frontier
            .iter()
            .map(|&i| {
                let (s, c) = neighbours[i]
                    .iter()
                    .filter(|&&j| ring[j as usize] < k)
                    .fold((V3::zeros(), 0usize), |(s, c), &j| {
                        (s + disp[j as usize], c + 1)
                    });
                (i, s / c.max(1) as f64)
            })
            .collect();
        for &(i, d) in &updates {
            disp[i] = d;
            ring[i] = k;
        }
        let mut next: Vec<usize> = updates
            .iter()
            .flat_map(|&(i, _)| neighbours[i].iter().map(|&j| j as usize))
            .filter(|&j| ring[j] == u32::MAX)
            .collect();
        next.sort_unstable();
        next.dedup();
        frontier = next;
    }
    ring
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fills_a_path_from_both_ends() {
        // 0 - 1 - 2 - 3 - 4, ends matched
        let nb = vec![vec![1], vec![0, 2], vec![1, 3], vec![2, 4], vec![3]];
        let matched = [true, false, false, false, true];
        let mut d = vec![
            V3::new(1., 0., 0.),
            V3::zeros(),
            V3::zeros(),
            V3::zeros(),
            V3::new(3., 0., 0.),
        ];
        let ring = grass_fire(&nb, &matched, &mut d);
        assert_eq!(ring, vec![0, 1, 2, 1, 0]);
        assert_eq!(d[1].x, 1.0);
        assert_eq!(d[3].x, 3.0);
        assert_eq!(d[2].x, 2.0);
    }
}
