//! Building and reading the simulator protocol's dense arrays (`Tensor`: raw little-endian bytes in C order) with
//! their dtype and shape checked.

use tonic::Status;

use crate::simulator::v1::{DType, Tensor};

impl Tensor {
    fn raw(dtype: DType, shape: &[usize], data: Vec<u8>) -> Tensor {
        Tensor {
            dtype: dtype as i32,
            shape: shape.iter().map(|&d| d as u64).collect(),
            data,
        }
    }

    pub fn from_f32(shape: &[usize], values: &[f32]) -> Tensor {
        Tensor::raw(
            DType::Float32,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    pub fn from_f64(shape: &[usize], values: &[f64]) -> Tensor {
        Tensor::raw(
            DType::Float64,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    pub fn from_bool(shape: &[usize], values: &[bool]) -> Tensor {
        Tensor::raw(DType::Bool, shape, values.iter().map(|&b| b as u8).collect())
    }

    /// The number of elements the shape declares, or `None` when it overflows.
    pub fn element_count(&self) -> Option<usize> {
        self.shape
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(usize::try_from(d).ok()?))
    }

    /// The element count when the tensor has dtype `want` (of `width` bytes) and its bytes hold its shape; an
    /// `INVALID_ARGUMENT` naming `name` otherwise.
    pub fn check(&self, name: &str, want: DType, width: usize) -> Result<usize, Status> {
        if self.dtype != want as i32 {
            let got = DType::try_from(self.dtype)
                .map(|d| d.as_str_name().to_owned())
                .unwrap_or(self.dtype.to_string());
            return Err(Status::invalid_argument(format!(
                "{name}: dtype {got}, expected {}",
                want.as_str_name()
            )));
        }
        let count = self
            .element_count()
            .filter(|n| n.checked_mul(width) == Some(self.data.len()));
        count.ok_or_else(|| {
            Status::invalid_argument(format!(
                "{name}: {} bytes do not hold shape {:?} of {}",
                self.data.len(),
                self.shape,
                want.as_str_name()
            ))
        })
    }

    pub fn to_f32(&self, name: &str) -> Result<Vec<f32>, Status> {
        self.check(name, DType::Float32, 4)?;
        Ok(self
            .data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect())
    }

    pub fn to_f64(&self, name: &str) -> Result<Vec<f64>, Status> {
        self.check(name, DType::Float64, 8)?;
        Ok(self
            .data
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect())
    }

    pub fn to_bool(&self, name: &str) -> Result<Vec<bool>, Status> {
        self.check(name, DType::Bool, 1)?;
        Ok(self.data.iter().map(|&b| b != 0).collect())
    }
}
