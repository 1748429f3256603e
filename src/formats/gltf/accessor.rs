//! Buffer views and accessors: every byte range is checked here, with checked arithmetic,
//! before a single element is read, so a lying file is an error naming the range and never
//! an out-of-bounds slice. Values come out as f64 (exact for every glTF component type).

use std::borrow::Cow;
use std::sync::Arc;

use gltf::json;
use gltf::json::accessor::{ComponentType, Type};
use gltf::json::validation::Checked;

use super::GltfError;

/// Most values (elements × components) that accessors without a bufferView (all zeros,
/// plus sparse substitutions) may hold, all such accessors of a file together. They cost
/// memory without costing file bytes, so they are bounded explicitly: 2^25 values (256 MiB
/// as f64) is far beyond real sparse use (a 5-million-vertex sparse morph target needs
/// 2^24). Everything else the loader allocates is bounded by the bytes of the file.
pub const MAX_VIEWLESS_VALUES: u64 = 1 << 25;

/// The checked byte layout of one accessor.
#[derive(Clone, Copy, Debug)]
pub(super) struct Layout {
    pub ty: Type,
    pub component: ComponentType,
    pub normalized: bool,
    pub count: usize,
    /// Size of one element in bytes, column padding of small matrices included.
    pub elem_size: usize,
}

/// Buffers and the document, with every view range already checked.
pub(super) struct Data<'a> {
    pub root: &'a json::Root,
    pub buffers: Vec<Cow<'a, [u8]>>,
    cache: Vec<Option<Arc<[f64]>>>,
    /// Values of view-less accessors read so far (see [`MAX_VIEWLESS_VALUES`]).
    viewless_values: u64,
}

fn components(ty: Type) -> usize {
    ty.multiplicity()
}

/// Byte size of one element. Matrix columns start on 4-byte boundaries, which pads MAT2
/// and MAT3 of 1-byte and MAT3 of 2-byte components.
fn element_size(ty: Type, c: ComponentType) -> usize {
    let (cols, rows) = match ty {
        Type::Mat2 => (2, 2),
        Type::Mat3 => (3, 3),
        Type::Mat4 => (4, 4),
        _ => (1, components(ty)),
    };
    if cols == 1 {
        rows * c.size()
    } else {
        cols * (rows * c.size()).next_multiple_of(4)
    }
}

/// Byte offset of component `k` inside an element.
fn component_offset(ty: Type, c: ComponentType, k: usize) -> usize {
    let rows = match ty {
        Type::Mat2 => 2,
        Type::Mat3 => 3,
        Type::Mat4 => 4,
        _ => return k * c.size(),
    };
    (k / rows) * (rows * c.size()).next_multiple_of(4) + (k % rows) * c.size()
}

pub(super) fn type_name(ty: Type) -> &'static str {
    match ty {
        Type::Scalar => "SCALAR",
        Type::Vec2 => "VEC2",
        Type::Vec3 => "VEC3",
        Type::Vec4 => "VEC4",
        Type::Mat2 => "MAT2",
        Type::Mat3 => "MAT3",
        Type::Mat4 => "MAT4",
    }
}

pub(super) fn component_name(c: ComponentType) -> &'static str {
    match c {
        ComponentType::I8 => "BYTE",
        ComponentType::U8 => "UNSIGNED_BYTE",
        ComponentType::I16 => "SHORT",
        ComponentType::U16 => "UNSIGNED_SHORT",
        ComponentType::U32 => "UNSIGNED_INT",
        ComponentType::F32 => "FLOAT",
    }
}

/// `offset + len`, or an error-friendly `u64::MAX` when that overflows.
fn end_of(offset: u64, len: u64) -> u64 {
    offset.saturating_add(len)
}

/// Reads one component and converts it to f64 with glTF's normalisation rules.
#[inline]
fn component_value(b: &[u8], c: ComponentType, normalized: bool) -> f64 {
    match c {
        ComponentType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ComponentType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ComponentType::I8 => {
            let v = b[0] as i8 as f64;
            if normalized {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U8 => {
            let v = b[0] as f64;
            if normalized {
                v / 255.0
            } else {
                v
            }
        }
        ComponentType::I16 => {
            let v = i16::from_le_bytes([b[0], b[1]]) as f64;
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U16 => {
            let v = u16::from_le_bytes([b[0], b[1]]) as f64;
            if normalized {
                v / 65535.0
            } else {
                v
            }
        }
    }
}

impl<'a> Data<'a> {
    /// Checks every buffer view against its buffer and every accessor (and its sparse
    /// parts) against its views. `buffers` are already cut to their `byteLength`.
    pub(super) fn new(
        root: &'a json::Root,
        buffers: Vec<Cow<'a, [u8]>>,
    ) -> Result<Data<'a>, GltfError> {
        for (v, view) in root.buffer_views.iter().enumerate() {
            let b = view.buffer.value();
            let Some(buffer) = buffers.get(b) else {
                return Err(GltfError::DanglingReference {
                    from: format!("bufferView {v}"),
                    kind: "buffer",
                    index: b,
                    count: buffers.len(),
                });
            };
            let offset = view.byte_offset.map_or(0, |o| o.0);
            let end = end_of(offset, view.byte_length.0);
            if end > buffer.len() as u64 {
                return Err(GltfError::BufferViewOutOfRange {
                    view: v,
                    buffer: b,
                    offset,
                    end,
                    buffer_length: buffer.len() as u64,
                });
            }
            if let Some(stride) = view.byte_stride {
                if !(4..=252).contains(&stride.0) || stride.0 % 4 != 0 {
                    return Err(GltfError::BadBufferView {
                        view: v,
                        reason: format!(
                            "byteStride {} is not a multiple of 4 in 4..=252",
                            stride.0
                        ),
                    });
                }
            }
        }
        let data = Data {
            root,
            buffers,
            cache: vec![None; root.accessors.len()],
            viewless_values: 0,
        };
        for a in 0..root.accessors.len() {
            data.layout(a)?;
        }
        Ok(data)
    }

    /// The accessor itself, or an error naming who referred to it.
    pub(super) fn accessor(
        &self,
        index: usize,
        from: &dyn Fn() -> String,
    ) -> Result<&'a json::Accessor, GltfError> {
        self.root
            .accessors
            .get(index)
            .ok_or_else(|| GltfError::DanglingReference {
                from: from(),
                kind: "accessor",
                index,
                count: self.root.accessors.len(),
            })
    }

    /// The view's bytes (within its buffer, already checked) and its stride.
    pub(super) fn view_bytes(&self, v: usize) -> Result<(&[u8], Option<usize>), GltfError> {
        let view = self
            .root
            .buffer_views
            .get(v)
            .ok_or(GltfError::DanglingReference {
                from: "an accessor".to_string(),
                kind: "bufferView",
                index: v,
                count: self.root.buffer_views.len(),
            })?;
        let buffer = &self.buffers[view.buffer.value()];
        let offset = view.byte_offset.map_or(0, |o| o.0) as usize;
        let len = view.byte_length.0 as usize;
        Ok((&buffer[offset..offset + len], view.byte_stride.map(|s| s.0)))
    }

    /// Checks accessor `a`'s type, ranges and sparse parts; reads nothing.
    pub(super) fn layout(&self, a: usize) -> Result<Layout, GltfError> {
        let acc = self.accessor(a, &|| "the document".to_string())?;
        let bad = |reason: String| GltfError::BadAccessor {
            accessor: a,
            reason,
        };
        let Checked::Valid(ty) = acc.type_ else {
            return Err(bad("invalid type".to_string()));
        };
        let Checked::Valid(gct) = acc.component_type else {
            return Err(bad("invalid componentType".to_string()));
        };
        let component = gct.0;
        if acc.normalized && component == ComponentType::U32 {
            return Err(bad("normalized UNSIGNED_INT is not allowed".to_string()));
        }
        let elem_size = element_size(ty, component);
        let count = acc.count.0;
        if let Some(v) = acc.buffer_view {
            let (bytes, stride) =
                self.view_bytes(v.value())
                    .map_err(|_| GltfError::DanglingReference {
                        from: format!("accessor {a}"),
                        kind: "bufferView",
                        index: v.value(),
                        count: self.root.buffer_views.len(),
                    })?;
            let stride = stride.unwrap_or(elem_size);
            if stride < elem_size {
                return Err(bad(format!(
                    "byteStride {stride} of bufferView {} is smaller than its {elem_size}-byte elements",
                    v.value()
                )));
            }
            let offset = acc.byte_offset.map_or(0, |o| o.0);
            if count > 0 {
                // offset + stride·(count−1) + elemSize, without overflow.
                let end = (count - 1)
                    .checked_mul(stride as u64)
                    .and_then(|x| x.checked_add(offset))
                    .and_then(|x| x.checked_add(elem_size as u64))
                    .unwrap_or(u64::MAX);
                if end > bytes.len() as u64 {
                    return Err(GltfError::AccessorOutOfRange {
                        accessor: a,
                        view: v.value(),
                        offset,
                        end,
                        view_length: bytes.len() as u64,
                    });
                }
            }
        } else {
            let values = count.saturating_mul(components(ty) as u64);
            if values > MAX_VIEWLESS_VALUES {
                return Err(GltfError::TooLarge {
                    accessor: a,
                    values,
                    limit: MAX_VIEWLESS_VALUES,
                });
            }
        }
        if let Some(sparse) = &acc.sparse {
            let n = sparse.count.0;
            if n > count {
                return Err(bad(format!(
                    "sparse count {n} exceeds the accessor's count {count}"
                )));
            }
            let Checked::Valid(ict) = sparse.indices.component_type else {
                return Err(bad("invalid sparse indices componentType".to_string()));
            };
            if !matches!(
                ict.0,
                ComponentType::U8 | ComponentType::U16 | ComponentType::U32
            ) {
                return Err(bad(
                    "sparse indices must be UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT"
                        .to_string(),
                ));
            }
            let parts = [
                (
                    "indices",
                    sparse.indices.buffer_view.value(),
                    sparse.indices.byte_offset.0,
                    ict.0.size() as u64,
                ),
                (
                    "values",
                    sparse.values.buffer_view.value(),
                    sparse.values.byte_offset.0,
                    elem_size as u64,
                ),
            ];
            for (part, v, offset, size) in parts {
                let (bytes, _) = self
                    .view_bytes(v)
                    .map_err(|_| GltfError::DanglingReference {
                        from: format!("accessor {a} sparse {part}"),
                        kind: "bufferView",
                        index: v,
                        count: self.root.buffer_views.len(),
                    })?;
                // Sparse data is tightly packed whatever the view's stride says.
                let end = n
                    .checked_mul(size)
                    .and_then(|x| x.checked_add(offset))
                    .unwrap_or(u64::MAX);
                if end > bytes.len() as u64 {
                    return Err(GltfError::SparseOutOfRange {
                        accessor: a,
                        part,
                        view: v,
                        offset,
                        end,
                        view_length: bytes.len() as u64,
                    });
                }
            }
        }
        Ok(Layout {
            ty,
            component,
            normalized: acc.normalized,
            // Bounded by the view length (stride ≥ elemSize ≥ 1) or MAX_VIEWLESS_VALUES.
            count: count as usize,
            elem_size,
        })
    }

    /// Reads accessor `a` as `count × components` f64 values (dense, sparse applied).
    /// Results are shared between users of the same accessor.
    pub(super) fn read(&mut self, a: usize) -> Result<Arc<[f64]>, GltfError> {
        if let Some(Some(v)) = self.cache.get(a) {
            return Ok(v.clone());
        }
        let l = self.layout(a)?;
        let acc = &self.root.accessors[a];
        let n = components(l.ty);
        if acc.buffer_view.is_none() {
            let values = (l.count * n) as u64;
            self.viewless_values += values;
            if self.viewless_values > MAX_VIEWLESS_VALUES {
                return Err(GltfError::TooLarge {
                    accessor: a,
                    values: self.viewless_values,
                    limit: MAX_VIEWLESS_VALUES,
                });
            }
        }
        let mut out = vec![0.0f64; l.count * n];
        let offsets: Vec<usize> = (0..n)
            .map(|k| component_offset(l.ty, l.component, k))
            .collect();
        let csize = l.component.size();
        if let Some(v) = acc.buffer_view {
            let (bytes, stride) = self.view_bytes(v.value())?;
            let stride = stride.unwrap_or(l.elem_size);
            let base = acc.byte_offset.map_or(0, |o| o.0) as usize;
            for (i, dst) in out.chunks_exact_mut(n).enumerate() {
                let e = base + i * stride;
                for (d, &o) in dst.iter_mut().zip(&offsets) {
                    *d = component_value(&bytes[e + o..e + o + csize], l.component, l.normalized);
                }
            }
        }
        if let Some(sparse) = &acc.sparse {
            let count = sparse.count.0 as usize;
            let Checked::Valid(ict) = sparse.indices.component_type else {
                // `layout` has refused this already; stay panic-free regardless.
                return Err(GltfError::BadAccessor {
                    accessor: a,
                    reason: "invalid sparse indices componentType".to_string(),
                });
            };
            let ict = ict.0;
            let (ibytes, _) = self.view_bytes(sparse.indices.buffer_view.value())?;
            let ibase = sparse.indices.byte_offset.0 as usize;
            let (vbytes, _) = self.view_bytes(sparse.values.buffer_view.value())?;
            let vbase = sparse.values.byte_offset.0 as usize;
            let isize = ict.size();
            for entry in 0..count {
                let at = ibase + entry * isize;
                let index = component_value(&ibytes[at..at + isize], ict, false) as usize;
                if index >= l.count {
                    return Err(GltfError::SparseIndexOutOfRange {
                        accessor: a,
                        entry,
                        index,
                        count: l.count,
                    });
                }
                let e = vbase + entry * l.elem_size;
                for (k, &o) in offsets.iter().enumerate() {
                    out[index * n + k] =
                        component_value(&vbytes[e + o..e + o + csize], l.component, l.normalized);
                }
            }
        }
        let rc: Arc<[f64]> = out.into();
        self.cache[a] = Some(rc.clone());
        Ok(rc)
    }
}

/// What one use of an accessor allows; the error says which use was wrong.
pub(super) struct Expect {
    /// The use, for the message ("POSITION of mesh 0 primitive 1").
    pub what: String,
    pub types: &'static [Type],
    /// Allowed `(componentType, normalized)` pairs; `None` for normalized means either.
    pub components: &'static [(ComponentType, Option<bool>)],
}

impl Expect {
    /// Checks layout `l` of accessor `a` against this use.
    pub(super) fn check(&self, a: usize, l: &Layout) -> Result<(), GltfError> {
        let comp_ok = self
            .components
            .iter()
            .any(|&(c, n)| c == l.component && n.unwrap_or(l.normalized) == l.normalized);
        if !self.types.contains(&l.ty) || !comp_ok {
            let allowed: Vec<String> = self
                .components
                .iter()
                .map(|&(c, n)| match n {
                    Some(true) => format!("normalized {}", component_name(c)),
                    Some(false) => component_name(c).to_string(),
                    None => format!("{} (normalized or not)", component_name(c)),
                })
                .collect();
            let types: Vec<&str> = self.types.iter().map(|&t| type_name(t)).collect();
            return Err(GltfError::BadAccessor {
                accessor: a,
                reason: format!(
                    "used as {} it must be {} of {}, but it is {}{} {}",
                    self.what,
                    types.join("/"),
                    allowed.join(", "),
                    if l.normalized { "normalized " } else { "" },
                    component_name(l.component),
                    type_name(l.ty),
                ),
            });
        }
        Ok(())
    }
}

/// Component rules for the uses the loader has.
pub(super) mod rules {
    use super::ComponentType::*;
    use super::*;

    pub const FLOAT: &[(ComponentType, Option<bool>)] = &[(F32, None)];
    /// KHR_mesh_quantization positions, translations and scales: FLOAT or any small integer
    /// type, normalized or not.
    pub const QUANTIZED: &[(ComponentType, Option<bool>)] = &[
        (F32, None),
        (I8, None),
        (U8, None),
        (I16, None),
        (U16, None),
    ];
    /// Morph target deltas under KHR_mesh_quantization: FLOAT or signed integers.
    pub const QUANTIZED_DELTA: &[(ComponentType, Option<bool>)] =
        &[(F32, None), (I8, None), (I16, None)];
    /// NORMAL and TANGENT (and their morph deltas) under KHR_mesh_quantization.
    pub const QUANTIZED_NORMAL: &[(ComponentType, Option<bool>)] =
        &[(F32, None), (I8, Some(true)), (I16, Some(true))];
    /// TEXCOORD_n without KHR_mesh_quantization.
    pub const TEXCOORD: &[(ComponentType, Option<bool>)] =
        &[(F32, None), (U8, Some(true)), (U16, Some(true))];
    /// COLOR_n.
    pub const COLOR: &[(ComponentType, Option<bool>)] =
        &[(F32, None), (U8, Some(true)), (U16, Some(true))];
    pub const INDICES: &[(ComponentType, Option<bool>)] =
        &[(U8, Some(false)), (U16, Some(false)), (U32, Some(false))];
    pub const JOINTS: &[(ComponentType, Option<bool>)] = &[(U8, Some(false)), (U16, Some(false))];
    pub const WEIGHTS: &[(ComponentType, Option<bool>)] =
        &[(F32, None), (U8, Some(true)), (U16, Some(true))];
    /// Rotations and morph weights in animation outputs.
    pub const NORMALIZED_OR_FLOAT: &[(ComponentType, Option<bool>)] = &[
        (F32, None),
        (I8, Some(true)),
        (U8, Some(true)),
        (I16, Some(true)),
        (U16, Some(true)),
    ];
}

impl Data<'_> {
    /// Reads accessor `a` after checking it suits `expect`; also returns its layout.
    pub(super) fn read_as(
        &mut self,
        a: usize,
        expect: &Expect,
    ) -> Result<(Arc<[f64]>, Layout), GltfError> {
        let l = self.layout(a)?;
        expect.check(a, &l)?;
        Ok((self.read(a)?, l))
    }

    /// The layout of accessor `a` after checking it suits `expect`, without reading.
    pub(super) fn layout_as(&self, a: usize, expect: &Expect) -> Result<Layout, GltfError> {
        let l = self.layout(a)?;
        expect.check(a, &l)?;
        Ok(l)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrix_padding() {
        assert_eq!(element_size(Type::Mat2, ComponentType::U8), 8);
        assert_eq!(element_size(Type::Mat3, ComponentType::U8), 12);
        assert_eq!(element_size(Type::Mat3, ComponentType::I16), 24);
        assert_eq!(element_size(Type::Mat4, ComponentType::F32), 64);
        assert_eq!(element_size(Type::Vec3, ComponentType::I16), 6);
        assert_eq!(component_offset(Type::Mat3, ComponentType::U8, 4), 5);
    }

    #[test]
    fn normalisation() {
        assert_eq!(component_value(&[0x80], ComponentType::I8, true), -1.0);
        assert_eq!(component_value(&[0x81], ComponentType::I8, true), -1.0);
        assert_eq!(component_value(&[255], ComponentType::U8, true), 1.0);
        assert_eq!(
            component_value(&[0xFF, 0x7F], ComponentType::I16, true),
            1.0
        );
        assert_eq!(component_value(&[7, 0], ComponentType::U16, false), 7.0);
    }
}
