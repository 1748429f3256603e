//! One spelling for every name: the enums that users name on the command line, in JSON
//! bodies and in query strings (accelerators, queries, hit formats, precisions, build
//! qualities, integrators, image formats, invalid-ray policies).
//!
//! Each enum's spelling lives in exactly one place, its serde attributes. [`spelled!`]
//! derives everything else from them: [`Spelled::name`] (the `&'static str` serde writes),
//! `FromStr` and `Display`, and clap's `ValueEnum`, so that `--accel dacrt-sampled`,
//! `{"accel": "dacrt-sampled"}` and `?accel=dacrt-sampled` agree by construction and
//! `--help` lists exactly the names JSON accepts.

/// An enum whose names come from its serde attributes.
pub trait Spelled: Sized + Copy + 'static + serde::Serialize + serde::de::DeserializeOwned {
    /// Every value, in the order they are listed to users.
    const ALL: &'static [Self];

    /// The contract's name of this value.
    fn name(self) -> &'static str {
        // A unit variant's serde name is a `&'static str` in the type's own metadata.
        serde_variant::to_variant_name(&self).expect("a unit variant always has a name")
    }

    /// Parses a name, or says which names exist.
    fn parse_name(s: &str) -> Result<Self, UnknownName> {
        Self::ALL
            .iter()
            .copied()
            .find(|v| v.name() == s)
            .ok_or_else(|| UnknownName {
                kind: std::any::type_name::<Self>()
                    .rsplit("::")
                    .next()
                    .unwrap_or("value"),
                given: s.to_string(),
                names: Self::ALL.iter().map(|v| v.name()).collect(),
            })
    }
}

/// A name that no value of the enum has.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown {} '{given}' (one of: {})", kind_words(kind), names.join(", "))]
pub struct UnknownName {
    /// The enum's type name.
    pub kind: &'static str,
    /// What was given.
    pub given: String,
    /// Every valid name.
    pub names: Vec<&'static str>,
}

/// `AccelKind` → "accel kind": how a type name reads in a message.
fn kind_words(kind: &str) -> String {
    let mut out = String::new();
    for (i, c) in kind.chars().enumerate() {
        if c.is_uppercase() && i > 0 {
            out.push(' ');
        }
        out.extend(c.to_lowercase());
    }
    out
}

/// Implements [`Spelled`], `FromStr`, `Display` and `clap::ValueEnum` for enums whose
/// serde attributes give their names, listing the values in user order.
#[macro_export]
macro_rules! spelled {
    ($t:ty, [$($v:expr),+ $(,)?]) => {
        $crate::spelled!(@impl $t, &[$($v),+]);
    };
    ($t:ty, $all:path) => {
        $crate::spelled!(@impl $t, &$all);
    };
    (@impl $t:ty, $all:expr) => {
        impl $crate::names::Spelled for $t {
            const ALL: &'static [Self] = $all;
        }
        impl ::std::str::FromStr for $t {
            type Err = $crate::names::UnknownName;
            fn from_str(s: &str) -> Result<Self, Self::Err> {
                <$t as $crate::names::Spelled>::parse_name(s)
            }
        }
        impl ::std::fmt::Display for $t {
            fn fmt(&self, f: &mut ::std::fmt::Formatter<'_>) -> ::std::fmt::Result {
                f.write_str($crate::names::Spelled::name(*self))
            }
        }
        impl ::clap::ValueEnum for $t {
            fn value_variants<'a>() -> &'a [Self] {
                <$t as $crate::names::Spelled>::ALL
            }
            fn to_possible_value(&self) -> Option<::clap::builder::PossibleValue> {
                Some(::clap::builder::PossibleValue::new(
                    $crate::names::Spelled::name(*self),
                ))
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::Spelled;
    use crate::accel::{AccelKind, BuildQuality, Precision, Query};
    use crate::formats::HitFormat;
    use crate::render::image::ImageFormat;
    use crate::render::Integrator;

    /// Every spelling round-trips through serde JSON, `FromStr` and clap.
    fn round_trip<T: Spelled + std::fmt::Debug + PartialEq + clap::ValueEnum>() {
        for &v in T::ALL {
            let json = serde_json::to_string(&v).unwrap();
            assert_eq!(json, format!("\"{}\"", v.name()));
            assert_eq!(serde_json::from_str::<T>(&json).unwrap(), v);
            assert_eq!(T::parse_name(v.name()).unwrap(), v);
            assert_eq!(T::from_str(v.name(), false).unwrap(), v);
        }
        assert!(T::parse_name("no-such-name").is_err());
    }

    #[test]
    fn every_enum_has_one_spelling() {
        round_trip::<AccelKind>();
        round_trip::<Query>();
        round_trip::<Precision>();
        round_trip::<BuildQuality>();
        round_trip::<HitFormat>();
        round_trip::<Integrator>();
        round_trip::<ImageFormat>();
        round_trip::<crate::jobs::InvalidPolicy>();
        round_trip::<crate::jobs::Update>();
    }

    #[test]
    fn the_contract_names() {
        assert_eq!(AccelKind::DacrtSampled.name(), "dacrt-sampled");
        assert_eq!(HitFormat::TPrimUv.name(), "t_prim_uv");
        assert_eq!(BuildQuality::Sbvh.name(), "sbvh");
        let e = AccelKind::parse_name("octree").unwrap_err();
        assert!(e.to_string().contains("unknown accel kind 'octree'"), "{e}");
        assert!(e.to_string().contains("dacrt-sampled"), "{e}");
    }
}
