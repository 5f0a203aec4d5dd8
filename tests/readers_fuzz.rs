//! Property tests: random bytes, and valid files cut short or with bytes changed, fed to
//! every reader. Each must return a mesh or an error, never panic.

use conformd::mesh::io::{
    PlyEncoding, obj_bytes, ply_bytes, read_obj_bytes, read_off_bytes, read_ply_bytes,
};
use conformd::mesh::landmarks::{parse_pp, parse_text};
use conformd::synth::icosphere;
use proptest::prelude::*;

fn samples() -> Vec<Vec<u8>> {
    let mut m = icosphere(1);
    m.normals = Some(m.vertex_normals());
    vec![
        ply_bytes(&m, PlyEncoding::Ascii),
        ply_bytes(&m, PlyEncoding::BinaryLittleEndian),
        obj_bytes(&m).into_bytes(),
        b"OFF\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n4 0 1 2 3\n".to_vec(),
        b"a 1\nb 2 3 4\n".to_vec(),
        br#"<PickedPoints><point x="1" y="2" z="3" name="a"/></PickedPoints>"#.to_vec(),
    ]
}

fn all_readers(bytes: &[u8]) {
    let _ = read_ply_bytes("f.ply", bytes);
    let _ = read_obj_bytes("f.obj", bytes);
    let _ = read_off_bytes("f.off", bytes);
    let _ = parse_text("f.txt", bytes);
    let _ = parse_pp("f.pp", bytes);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        all_readers(&bytes);
    }

    #[test]
    fn headers_with_random_bodies_never_panic(which in 0usize..2, body in proptest::collection::vec(any::<u8>(), 0..512)) {
        let s = &samples()[which];
        let end = s.windows(10).position(|w| w == b"end_header").unwrap() + 11;
        let mut bytes = s[..end].to_vec();
        bytes.extend_from_slice(&body);
        all_readers(&bytes);
    }

    #[test]
    fn cut_or_mutated_files_never_panic(which in 0usize..6, cut in 0.0f64..1.0, flips in proptest::collection::vec((0.0f64..1.0, any::<u8>()), 0..8)) {
        let mut bytes = samples()[which].clone();
        for (at, b) in flips {
            let i = ((bytes.len() as f64) * at) as usize;
            if i < bytes.len() { bytes[i] = b; }
        }
        let keep = ((bytes.len() as f64) * cut) as usize;
        all_readers(&bytes[..keep]);
        all_readers(&bytes);
    }
}
