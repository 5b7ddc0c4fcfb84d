//! candle's backward pass as the networks use it, with the workspace's patched candle-core
//! (`vendor/README.md`): a gradient reaching a tensor once is stored as it is, gradients
//! reaching it several times add up, and subtraction still subtracts.

use candle_core::{Device, Tensor, Var};
use ic_nn::ops::cpu::to_f32_vec;

#[test]
fn the_first_gradient_reaching_a_tensor_is_stored_as_is_not_added_to_zeros() {
    // d(sum(x·a))/dx = a. Stored as is, a −0.0 entry of `a` stays −0.0; added into fresh zeros
    // (candle 0.11.1 unpatched) it would become +0.0. This test fails if the patch is dropped.
    let x = Var::new(&[1.0f32, 2.0, 3.0], &Device::Cpu).unwrap();
    let a = Tensor::new(&[-0.0f32, 2.0, -3.0], &Device::Cpu).unwrap();
    let loss = (x.as_tensor() * &a).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let g = to_f32_vec(grads.get(&x).unwrap()).unwrap();
    assert_eq!(g, vec![0.0, 2.0, -3.0]);
    assert!(
        g[0].is_sign_negative(),
        "gradient {g:?}: the −0.0 was added to zeros"
    );
}

#[test]
fn gradients_reaching_a_tensor_twice_add_up_and_subtraction_subtracts() {
    let dev = Device::Cpu;
    let x = Var::new(&[[1.0f32, -2.0], [3.0, 0.5]], &dev).unwrap();
    let a = Tensor::new(&[[2.0f32, 3.0], [4.0, 5.0]], &dev).unwrap();
    let b = Tensor::new(&[[0.5f32, -1.0], [0.25, 2.0]], &dev).unwrap();
    let xt = x.as_tensor();
    // x·a + x·b − (x·b)ᵀᵀ·2 reaches x three times (the last through a transposed view):
    // the gradient is a + b − 2b = a − b.
    let twice = (xt * &b).unwrap().t().unwrap().t().unwrap();
    let y = ((xt * &a).unwrap() + (xt * &b).unwrap()).unwrap();
    let y = (y - (twice * 2.0).unwrap()).unwrap();
    let grads = y.sum_all().unwrap().backward().unwrap();
    let g = grads.get(&x).unwrap();
    assert!(g.is_contiguous());
    assert_eq!(to_f32_vec(g).unwrap(), vec![1.5, 4.0, 3.75, 3.0]);
    // A gradient that reaches a tensor only through a transpose is stored contiguous.
    let m = Tensor::new(&[[1.0f32, 2.0], [3.0, 4.0]], &dev).unwrap();
    let grads = (xt.t().unwrap() * &m)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let g = grads.get(&x).unwrap();
    assert!(g.is_contiguous());
    assert_eq!(to_f32_vec(g).unwrap(), vec![1.0, 3.0, 2.0, 4.0]);
}
