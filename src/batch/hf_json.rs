//! The Hugging Face `datasets` metadata of a Parquet file (the `huggingface`
//! key, `{"info": {"features": {...}}}`), read and written with its keys in
//! their order: `datasets` lists features in that order, and serde_json's
//! own map sorts them.

use serde::de::{Deserialize, Deserializer, MapAccess, SeqAccess, Visitor};
use serde::ser::{Serialize, SerializeMap, SerializeSeq, Serializer};

/// A JSON value whose objects keep their keys' order.
#[derive(Clone, Debug, PartialEq)]
pub enum Ordered {
    Null,
    Bool(bool),
    Number(serde_json::Number),
    String(String),
    Array(Vec<Ordered>),
    Object(Vec<(String, Ordered)>),
}

impl Ordered {
    /// The value of `key` in an object.
    pub fn get_mut(&mut self, key: &str) -> Option<&mut Ordered> {
        match self {
            Ordered::Object(pairs) => pairs.iter_mut().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }
}

/// `huggingface` metadata with a string feature `column` added at the end
/// of `info.features`; `None` when the text is not such metadata or already has it.
pub fn add_string_feature(metadata: &str, column: &str) -> Option<String> {
    let mut value: Ordered = serde_json::from_str(metadata).ok()?;
    let features = value.get_mut("info")?.get_mut("features")?;
    let Ordered::Object(pairs) = features else { return None };
    if pairs.iter().any(|(k, _)| k == column) {
        return None;
    }
    pairs.push((
        column.to_string(),
        Ordered::Object(vec![
            ("dtype".into(), Ordered::String("string".into())),
            ("_type".into(), Ordered::String("Value".into())),
        ]),
    ));
    serde_json::to_string(&value).ok()
}

impl Serialize for Ordered {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Ordered::Null => s.serialize_unit(),
            Ordered::Bool(b) => s.serialize_bool(*b),
            Ordered::Number(n) => n.serialize(s),
            Ordered::String(t) => s.serialize_str(t),
            Ordered::Array(items) => {
                let mut seq = s.serialize_seq(Some(items.len()))?;
                for item in items {
                    seq.serialize_element(item)?;
                }
                seq.end()
            }
            Ordered::Object(pairs) => {
                let mut map = s.serialize_map(Some(pairs.len()))?;
                for (k, v) in pairs {
                    map.serialize_entry(k, v)?;
                }
                map.end()
            }
        }
    }
}

impl<'de> Deserialize<'de> for Ordered {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Ordered, D::Error> {
        d.deserialize_any(OrderedVisitor)
    }
}

struct OrderedVisitor;

impl<'de> Visitor<'de> for OrderedVisitor {
    type Value = Ordered;
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_unit<E>(self) -> Result<Ordered, E> {
        Ok(Ordered::Null)
    }
    fn visit_none<E>(self) -> Result<Ordered, E> {
        Ok(Ordered::Null)
    }
    fn visit_bool<E>(self, v: bool) -> Result<Ordered, E> {
        Ok(Ordered::Bool(v))
    }
    fn visit_i64<E>(self, v: i64) -> Result<Ordered, E> {
        Ok(Ordered::Number(v.into()))
    }
    fn visit_u64<E>(self, v: u64) -> Result<Ordered, E> {
        Ok(Ordered::Number(v.into()))
    }
    fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Ordered, E> {
        serde_json::Number::from_f64(v)
            .map(Ordered::Number)
            .ok_or_else(|| E::custom("a number JSON cannot hold"))
    }
    fn visit_str<E>(self, v: &str) -> Result<Ordered, E> {
        Ok(Ordered::String(v.to_string()))
    }
    fn visit_string<E>(self, v: String) -> Result<Ordered, E> {
        Ok(Ordered::String(v))
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Ordered, A::Error> {
        let mut items = Vec::new();
        while let Some(item) = seq.next_element()? {
            items.push(item);
        }
        Ok(Ordered::Array(items))
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Ordered, A::Error> {
        let mut pairs = Vec::new();
        while let Some((k, v)) = map.next_entry::<String, Ordered>()? {
            pairs.push((k, v));
        }
        Ok(Ordered::Object(pairs))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_id_feature_goes_last_and_the_order_of_the_others_is_kept() {
        let hf = r#"{"info":{"features":{"view_id":{"dtype":"int32","_type":"Value"},"rgb":{"_type":"Image"},"boxes_2d":[{"x1":{"dtype":"float32","_type":"Value"},"label":{"dtype":"string","_type":"Value"}}],"depth":{"_type":"Image"}}}}"#;
        let out = add_string_feature(hf, "scan").unwrap();
        assert_eq!(
            out,
            hf.replace(
                r#""depth":{"_type":"Image"}}"#,
                r#""depth":{"_type":"Image"},"scan":{"dtype":"string","_type":"Value"}}"#
            )
        );
        assert_eq!(add_string_feature(&out, "scan"), None, "already there");
        assert_eq!(add_string_feature("{\"info\": 3}", "scan"), None);
        assert_eq!(add_string_feature("not json", "scan"), None);
    }
}
