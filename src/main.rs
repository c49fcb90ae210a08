use burn::tensor::Tensor;
fn main() {
    let _ = std::any::type_name::<Tensor<2>>();
    let _ = foxglove::messages::PointCloud::default();
}
