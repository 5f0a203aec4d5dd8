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

/// The manifest, rig and station readers: a valid file of each, cut short or with bytes
/// changed, or random bytes, must give a value or an error, never a panic; a station file
/// error names a line whenever the parser knows one.
mod config_readers {
    use conformd::devices::capture_set::Manifest;
    use conformd::station::StationConfig;
    use conformd::stereo::rig::RigFile;
    use proptest::prelude::*;
    use std::path::Path;

    const MANIFEST: &str = r#"{"format":"conformd-capture","version":1,"id":"20261201T101010.000Z-000","station":"crate-1","subject":"pig-7","started_utc":"20261201T101010.000Z","finished_utc":"20261201T101010.100Z","trigger":{"kind":"serial","sequence":3,"box_time_us":12345},"cameras":[{"id":"pod1-left","pod":"pod1","side":"left","file":"pod1-left.png","width":640,"height":480,"sensor_timestamp_us":1,"sequence":1,"exposure_us":8000},{"id":"pod1-right","pod":"pod1","side":"right","file":"pod1-right.png","width":640,"height":480,"sensor_timestamp_us":2,"sequence":1,"exposure_us":null}]}"#;

    fn samples() -> [String; 3] {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        [
            MANIFEST.to_string(),
            std::fs::read_to_string(root.join("rig.example.toml")).unwrap(),
            std::fs::read_to_string(root.join("station.example.toml")).unwrap(),
        ]
    }

    fn all(bytes: &[u8]) {
        let text = String::from_utf8_lossy(bytes);
        let _ = Manifest::parse(bytes);
        let _ = RigFile::parse("rig.toml", &text);
        if let Err(e) = StationConfig::parse(&text, Path::new("/etc/conformd/station.toml")) {
            assert!(!e.problems.is_empty());
        }
    }

    #[test]
    fn the_samples_are_valid() {
        let [m, r, s] = samples();
        Manifest::parse(m.as_bytes()).unwrap();
        RigFile::parse("rig.toml", &r).unwrap();
        StationConfig::parse(&s, Path::new("/etc/conformd/station.toml")).unwrap();
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
            all(&bytes);
        }

        #[test]
        fn cut_or_mutated_files_never_panic(which in 0usize..3, cut in 0.0f64..1.0, flips in proptest::collection::vec((0.0f64..1.0, any::<u8>()), 0..8)) {
            let mut bytes = samples()[which].clone().into_bytes();
            for (at, b) in flips {
                let i = ((bytes.len() as f64) * at) as usize;
                if i < bytes.len() { bytes[i] = b; }
            }
            let keep = ((bytes.len() as f64) * cut) as usize;
            all(&bytes[..keep]);
            all(&bytes);
        }

        #[test]
        fn a_station_value_replaced_is_refused_with_its_line_or_taken(line in 0usize..120, value in prop_oneof![
            Just("-1".to_string()), Just("nan".to_string()), Just("1e309".to_string()),
            Just("\"../../x\"".to_string()), Just("[]".to_string()), Just("true".to_string()),
            Just("99999999999".to_string()), Just("\"\"".to_string()),
        ]) {
            let text = samples()[2].clone();
            let lines: Vec<&str> = text.lines().collect();
            let i = line % lines.len();
            let Some((key, _)) = lines[i].split_once(" = ") else { return Ok(()); };
            if key.starts_with('#') { return Ok(()); }
            let mut changed: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
            changed[i] = format!("{key} = {value}");
            let changed = changed.join("\n");
            if let Err(e) = StationConfig::parse(&changed, Path::new("/etc/conformd/station.toml")) {
                for p in &e.problems {
                    prop_assert!(p.line.is_some(), "no line for: {}", p.msg);
                }
            }
        }
    }
}
