use super::*;

#[test]
fn weight_maps_are_inverse() {
    let w = [0.1, 0.4, 0.3, 0.2];
    for k in 1..=3 {
        let (side, c) = weights_to_child(w, k);
        let back = weights_to_parent(c, k, side);
        for i in 0..4 {
            assert!((back[i] - w[i]).abs() < 1e-15);
        }
        let w2 = [0.4, 0.1, 0.3, 0.2];
        let (side, c) = weights_to_child(w2, k);
        let back = weights_to_parent(c, k, side);
        for i in 0..4 {
            assert!((back[i] - w2[i]).abs() < 1e-15, "k={k} side={side}");
        }
    }
}

#[test]
fn child_node_formula() {
    assert_eq!(
        child_nodes([0, 1, 2, 3], 3, 9),
        [[0, 1, 2, 9], [1, 2, 3, 9]]
    );
    assert_eq!(
        child_nodes([0, 1, 2, 3], 2, 9),
        [[0, 1, 9, 3], [1, 2, 9, 3]]
    );
    assert_eq!(
        child_nodes([0, 1, 2, 3], 1, 9),
        [[0, 9, 2, 3], [1, 9, 2, 3]]
    );
}
