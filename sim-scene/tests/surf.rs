//! The `.surf` surface-recording format: round trip, the byte layout of the module docs,
//! every rejection, divergence between recordings, and a reader that never panics.

use cosurg_sim_scene::surf::{
    DivergenceSample, SURF_MAGIC, SurfError, SurfaceRecord, SurfaceRecording, surface_divergence,
};
use nalgebra::Vector3;
use proptest::prelude::*;

fn small_recording() -> SurfaceRecording {
    SurfaceRecording {
        scene_hash: "abc".into(),
        interval_s: 0.05,
        surface_sizes: vec![2, 1],
        records: (0..3)
            .map(|k| SurfaceRecord {
                time_s: 0.05 * k as f64,
                vertices: vec![[k as f32, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]],
            })
            .collect(),
    }
}

/// Header: magic, hash length + hash, interval, surface count + sizes; then records of
/// time + 3 × f32 per vertex — written out by hand from the documented layout.
#[test]
fn bytes_follow_the_documented_layout_and_round_trip() {
    let r = small_recording();
    let mut want = b"CSURF01\n".to_vec();
    want.extend_from_slice(&3u32.to_le_bytes());
    want.extend_from_slice(b"abc");
    want.extend_from_slice(&0.05f64.to_le_bytes());
    want.extend_from_slice(&2u32.to_le_bytes());
    want.extend_from_slice(&2u32.to_le_bytes());
    want.extend_from_slice(&1u32.to_le_bytes());
    for rec in &r.records {
        want.extend_from_slice(&rec.time_s.to_le_bytes());
        for v in &rec.vertices {
            for c in v {
                want.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    assert_eq!(&want[..8], SURF_MAGIC);
    assert_eq!(r.to_bytes(), want);
    let mut file = Vec::new();
    r.write_to(&mut file).unwrap();
    assert_eq!(file, want);
    assert_eq!(SurfaceRecording::from_bytes(&want).unwrap(), r);
    assert_eq!(r.vertex_count(), 3);
}

#[test]
fn malformed_files_are_rejected_with_the_reason() {
    let good = small_recording().to_bytes();
    let header = good.len() - 3 * (8 + 12 * 3);
    assert_eq!(
        SurfaceRecording::from_bytes(b"nope"),
        Err(SurfError::BadMagic)
    );
    let mut other_version = good.clone();
    other_version[6] = b'2';
    assert_eq!(
        SurfaceRecording::from_bytes(&other_version),
        Err(SurfError::BadMagic)
    );
    assert!(matches!(
        SurfaceRecording::from_bytes(&good[..10]),
        Err(SurfError::Truncated {
            what: "hash length",
            ..
        })
    ));
    assert!(matches!(
        SurfaceRecording::from_bytes(&good[..good.len() - 1]),
        Err(SurfError::PartialRecord {
            remaining: 43,
            record_size: 44
        })
    ));
    // The header alone is a recording without records.
    assert_eq!(
        SurfaceRecording::from_bytes(&good[..header])
            .unwrap()
            .records,
        vec![]
    );
    let mut long_hash = good.clone();
    long_hash[8..12].copy_from_slice(&2000u32.to_le_bytes());
    assert!(matches!(
        SurfaceRecording::from_bytes(&long_hash),
        Err(SurfError::TooLarge {
            what: "scene hash length",
            ..
        })
    ));
    let mut not_utf8 = good.clone();
    not_utf8[12] = 0xff;
    assert_eq!(
        SurfaceRecording::from_bytes(&not_utf8),
        Err(SurfError::HashNotUtf8)
    );
    let mut zero_interval = good.clone();
    zero_interval[15..23].copy_from_slice(&0f64.to_le_bytes());
    assert_eq!(
        SurfaceRecording::from_bytes(&zero_interval),
        Err(SurfError::BadInterval(0.0))
    );
    let mut many_vertices = good[..header].to_vec();
    many_vertices[27..31].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        SurfaceRecording::from_bytes(&many_vertices),
        Err(SurfError::TooLarge {
            what: "vertex count",
            ..
        })
    ));
    let mut backwards = small_recording();
    backwards.records[2].time_s = 0.05;
    assert!(matches!(
        SurfaceRecording::from_bytes(&backwards.to_bytes()),
        Err(SurfError::BadTime { index: 2, .. })
    ));
    let mut nan = small_recording();
    nan.records[1].vertices[2][1] = f32::NAN;
    assert_eq!(
        SurfaceRecording::from_bytes(&nan.to_bytes()),
        Err(SurfError::NonFinite { index: 1 })
    );
}

/// Divergence per shared mark against distances worked out by hand; recordings of other
/// scenes or surfaces are not compared.
#[test]
fn divergence_between_recordings() {
    let a = small_recording();
    let mut b = small_recording();
    // Mark 1 only in `a`: not compared; mark 2: one of three vertices 3-4-5 away.
    b.records.remove(1);
    b.records[1].vertices[0][1] += 3.0;
    b.records[1].vertices[0][2] += 4.0;
    let div = a.divergence(&b).unwrap();
    assert_eq!(div.len(), 2);
    assert_eq!(
        div[0],
        DivergenceSample {
            time_s: 0.0,
            max_m: 0.0,
            rms_m: 0.0
        }
    );
    assert_eq!(div[1].time_s, 0.1);
    assert_eq!(div[1].max_m, 5.0);
    assert!((div[1].rms_m - (25.0f64 / 3.0).sqrt()).abs() < 1e-12);
    let mut other_scene = small_recording();
    other_scene.scene_hash = "x".into();
    assert!(matches!(
        a.divergence(&other_scene),
        Err(SurfError::Mismatch {
            what: "scene hash",
            ..
        })
    ));
    let mut other_sizes = small_recording();
    other_sizes.surface_sizes = vec![1, 2];
    assert!(matches!(
        a.divergence(&other_sizes),
        Err(SurfError::Mismatch {
            what: "surface sizes",
            ..
        })
    ));
    let v = |x: f64| Vector3::new(x, 0.0, 0.0);
    assert_eq!(surface_divergence(&[], &[v(1.0)]), (0.0, 0.0));
    // Only the first two vertices are compared: distances 1 and 3.
    let (max, rms) = surface_divergence(&[v(0.0), v(0.0), v(9.0)], &[v(1.0), v(3.0)]);
    assert_eq!(max, 3.0);
    assert!((rms - 5.0f64.sqrt()).abs() < 1e-12);
}

/// A vertex moving at 2 m/s along x (marks 50 ms apart) and another jumping 7 m at one
/// mark: the largest motion within a window is the larger of the speed times the widest
/// mark gap that fits and the jump (worked out by hand).
#[test]
fn motion_around_each_mark_and_within_a_window() {
    let mut r = SurfaceRecording {
        scene_hash: "abc".into(),
        interval_s: 0.05,
        surface_sizes: vec![2],
        records: (0..10)
            .map(|k| {
                let t = 0.05 * k as f64;
                let jump = if k >= 6 { 7.0 } else { 0.0 };
                SurfaceRecord {
                    time_s: t,
                    vertices: vec![[(2.0 * t) as f32, 0.0, 0.0], [0.0, jump, 0.0]],
                }
            })
            .collect(),
    };
    let near = |a: f64, b: f64| (a - b).abs() < 1e-6;
    let largest =
        |r: &SurfaceRecording, w: f64| r.motion_around(w).iter().map(|m| m.1).fold(0.0, f64::max);
    // Within 0.2 s: 4 gaps of 50 ms at 2 m/s = 0.4 m < the 7 m jump.
    assert!(near(largest(&r, 0.2), 7.0));
    // Without the jump: the mover's 0.4 m; a window shorter than a gap sees nothing.
    for rec in &mut r.records {
        rec.vertices[1] = [0.0; 3];
    }
    assert!(near(largest(&r, 0.2), 0.4));
    assert!(near(largest(&r, 0.12), 0.2));
    assert_eq!(largest(&r, 0.01), 0.0);
    // Around each mark: the mover covers 0.1 m in one 50 ms gap, at the ends too.
    let around = r.motion_around(0.05);
    assert_eq!(around.len(), 10);
    assert!(near(around[0].1, 0.1) && near(around[9].1, 0.1));
    assert!(around[1..9].iter().all(|m| near(m.1, 0.1)));
    assert!(near(around[3].0, 0.15));
    r.records.truncate(1);
    assert_eq!(largest(&r, 1.0), 0.0);
}

proptest! {
    #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn reader_never_panics_on_garbage(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = SurfaceRecording::from_bytes(&bytes);
        let mut with_magic = SURF_MAGIC.to_vec();
        with_magic.extend_from_slice(&bytes);
        let _ = SurfaceRecording::from_bytes(&with_magic);
    }

    #[test]
    fn reader_rejects_truncation_and_survives_corruption(cut in 0usize..200, flip in 0usize..200, bit in 0u8..8) {
        let r = small_recording();
        let bytes = r.to_bytes();
        let header = bytes.len() - 3 * (8 + 12 * 3);
        let cut = cut.min(bytes.len());
        let res = SurfaceRecording::from_bytes(&bytes[..cut]);
        let whole = cut >= header && (cut - header).is_multiple_of(8 + 12 * 3);
        prop_assert_eq!(res.is_ok(), whole, "cut at {}: {:?}", cut, res);
        if let Ok(t) = res {
            prop_assert_eq!(&t.records[..], &r.records[..t.records.len()]);
        }
        let mut corrupt = bytes.clone();
        let i = flip % corrupt.len();
        corrupt[i] ^= 1 << bit;
        let _ = SurfaceRecording::from_bytes(&corrupt);
    }
}
