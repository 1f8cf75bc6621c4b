//! Codec throughput: `cargo bench -p cosurg-proto`.

use cosurg_proto::*;

fn main() {
    divan::main();
}

fn pose() -> Message {
    Message::ToolPose(ToolPose {
        site: 3,
        tool: 1,
        sim_time_s: 12.345,
        position: [0.01, 0.02, 0.03],
        orientation: [1.0, 0.0, 0.0, 0.0],
        jaw_rad: 0.3,
        velocity: [0.1, 0.0, 0.0],
        angular_velocity: [0.0, 0.0, 1.0],
    })
}

fn keyframe(nodes: usize) -> Message {
    let ids: Vec<u32> = (0..nodes as u32).collect();
    let pos: Vec<[f64; 3]> = ids
        .iter()
        .map(|&i| {
            [
                (i % 17) as f64 * 1e-3,
                (i % 13) as f64 * 1e-3,
                (i % 11) as f64 * 1e-3,
            ]
        })
        .collect();
    let vel = vec![[0.001, -0.002, 0.0005]; nodes];
    Message::Keyframe(RegionKeyframe {
        region: 1,
        keyframe_id: 7,
        owner: 2,
        sim_time: 1.0,
        epoch: 0,
        tree_bits: vec![0xA5; nodes / 4],
        nodes: QuantisedNodes::encode_default(&ids, &pos, &vel).unwrap(),
        topology: 0,
    })
}

#[divan::bench]
fn encode_tool_pose(b: divan::Bencher) {
    let m = pose();
    b.bench(|| encode(divan::black_box(&m)));
}

#[divan::bench]
fn decode_tool_pose(b: divan::Bencher) {
    let bytes = encode(&pose());
    b.bench(|| decode(divan::black_box(&bytes)).unwrap());
}

#[divan::bench(args = [100, 1000, 10000])]
fn encode_keyframe(b: divan::Bencher, nodes: usize) {
    let m = keyframe(nodes);
    b.bench(|| encode(divan::black_box(&m)));
}

#[divan::bench(args = [100, 1000, 10000])]
fn decode_keyframe(b: divan::Bencher, nodes: usize) {
    let bytes = encode(&keyframe(nodes));
    b.bench(|| decode(divan::black_box(&bytes)).unwrap());
}

#[divan::bench(args = [1000, 10000])]
fn quantise_nodes(b: divan::Bencher, nodes: usize) {
    let ids: Vec<u32> = (0..nodes as u32).collect();
    let pos: Vec<[f64; 3]> = ids.iter().map(|&i| [i as f64 * 1e-5, 0.01, 0.02]).collect();
    let vel = vec![[0.0; 3]; nodes];
    b.bench(|| QuantisedNodes::encode_default(&ids, &pos, &vel).unwrap());
}
