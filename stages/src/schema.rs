//! Arrow schemas of every table, loaded from the JSON files in `data_schema/` (embedded at build
//! time), and the small type grammar those files use.
//!
//! A schema file looks like
//! ```json
//! { "table": "cameras", "doc": "...",
//!   "fields": [ { "name": "frame", "type": "uint32", "doc": "..." },
//!               { "name": "cam_to_world", "type": "fixed_size_list<float64, 16>" } ] }
//! ```
//! Types: `bool`, `int8..int64`, `uint8..uint64`, `float32`, `float64`, `utf8`, `binary`,
//! `list<T>`, `fixed_size_list<T, N>`. Fields are non-nullable unless `"nullable": true`;
//! list items are always non-nullable and named `item`.

use std::{collections::BTreeMap, sync::Arc, sync::OnceLock};

use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use serde::Deserialize;

include!(concat!(env!("OUT_DIR"), "/schema_files.rs"));

/// One schema file as written in `data_schema/`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SchemaFile {
    pub table: String,
    #[serde(default)]
    pub doc: String,
    pub fields: Vec<FieldFile>,
}

/// One column of a schema file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldFile {
    pub name: String,
    #[serde(rename = "type")]
    pub ty: String,
    #[serde(default)]
    pub nullable: bool,
    #[serde(default)]
    pub doc: String,
}

/// Parses a type expression of the schema grammar.
pub fn parse_type(s: &str) -> Result<DataType, String> {
    let s = s.trim();
    let inner = |prefix: &str| -> Option<&str> {
        s.strip_prefix(prefix)
            .and_then(|r| r.trim_start().strip_prefix('<'))
            .and_then(|r| r.strip_suffix('>'))
    };
    if let Some(args) = inner("fixed_size_list") {
        let (t, n) = args
            .rsplit_once(',')
            .ok_or_else(|| format!("`{s}`: expected fixed_size_list<T, N>"))?;
        let n: i32 = n
            .trim()
            .parse()
            .map_err(|_| format!("`{s}`: bad list size `{}`", n.trim()))?;
        return Ok(DataType::FixedSizeList(list_item(parse_type(t)?), n));
    }
    if let Some(t) = inner("list") {
        return Ok(DataType::List(list_item(parse_type(t)?)));
    }
    Ok(match s {
        "bool" => DataType::Boolean,
        "int8" => DataType::Int8,
        "int16" => DataType::Int16,
        "int32" => DataType::Int32,
        "int64" => DataType::Int64,
        "uint8" => DataType::UInt8,
        "uint16" => DataType::UInt16,
        "uint32" => DataType::UInt32,
        "uint64" => DataType::UInt64,
        "float32" => DataType::Float32,
        "float64" => DataType::Float64,
        "utf8" => DataType::Utf8,
        "binary" => DataType::Binary,
        other => return Err(format!("unknown type `{other}`")),
    })
}

/// Writes a data type in the schema grammar (the inverse of [`parse_type`]).
pub fn format_type(t: &DataType) -> String {
    match t {
        DataType::Boolean => "bool".into(),
        DataType::List(f) => format!("list<{}>", format_type(f.data_type())),
        DataType::FixedSizeList(f, n) => {
            format!("fixed_size_list<{}, {n}>", format_type(f.data_type()))
        }
        DataType::Utf8 => "utf8".into(),
        DataType::Binary => "binary".into(),
        other => format!("{other:?}").to_lowercase(),
    }
}

/// The item field every list column uses.
pub fn list_item(t: DataType) -> Arc<Field> {
    Arc::new(Field::new("item", t, false))
}

/// Builds an Arrow schema from a schema file's text.
pub fn schema_from_json(text: &str) -> Result<(SchemaFile, SchemaRef), String> {
    let file: SchemaFile = serde_json::from_str(text).map_err(|e| e.to_string())?;
    let mut fields = Vec::with_capacity(file.fields.len());
    for f in &file.fields {
        let t = parse_type(&f.ty).map_err(|e| format!("field `{}`: {e}", f.name))?;
        fields.push(Field::new(&f.name, t, f.nullable));
    }
    Ok((file, Arc::new(Schema::new(fields))))
}

fn all() -> &'static BTreeMap<&'static str, SchemaRef> {
    static ALL: OnceLock<BTreeMap<&'static str, SchemaRef>> = OnceLock::new();
    ALL.get_or_init(|| {
        SCHEMA_FILES
            .iter()
            .map(|(name, text)| {
                // A broken schema file is a build defect, caught by the schema tests.
                let (_, schema) = schema_from_json(text)
                    .unwrap_or_else(|e| panic!("data_schema/{name}.json: {e}"));
                (*name, schema)
            })
            .collect()
    })
}

/// The schema of table `name`, from `data_schema/<name>.json`.
pub fn get(name: &str) -> Option<SchemaRef> {
    all().get(name).cloned()
}

/// Names of every table that has a schema file.
pub fn names() -> impl Iterator<Item = &'static str> {
    SCHEMA_FILES.iter().map(|(n, _)| *n)
}

/// Checks that `actual` has exactly the columns and types of table `name`'s schema file.
pub fn check(name: &str, actual: &Schema) -> Result<(), String> {
    let expected = get(name).ok_or_else(|| format!("no schema file data_schema/{name}.json"))?;
    let show = |s: &Schema| {
        s.fields()
            .iter()
            .map(|f| {
                format!(
                    "{}: {}{}",
                    f.name(),
                    format_type(f.data_type()),
                    if f.is_nullable() { "?" } else { "" }
                )
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    let strip = |s: &Schema| Schema::new(s.fields().clone());
    if strip(&expected) != strip(actual) {
        return Err(format!(
            "table `{name}` does not match data_schema/{name}.json\n  expected: {}\n  written:  {}",
            show(&expected),
            show(actual)
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_schema_file_parses_and_names_itself() {
        assert!(!SCHEMA_FILES.is_empty());
        for (name, text) in SCHEMA_FILES {
            let (file, schema) = schema_from_json(text).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(
                &file.table, name,
                "data_schema/{name}.json names table `{}`",
                file.table
            );
            assert!(!schema.fields().is_empty(), "{name} has no fields");
        }
    }

    #[test]
    fn type_grammar_round_trips() {
        for t in [
            "uint8",
            "float64",
            "list<float32>",
            "fixed_size_list<float64, 16>",
            "list<list<uint32>>",
            "binary",
            "utf8",
            "bool",
        ] {
            assert_eq!(format_type(&parse_type(t).unwrap()), t);
        }
        assert!(parse_type("float128").is_err());
        assert!(parse_type("fixed_size_list<float32>").is_err());
    }
}
