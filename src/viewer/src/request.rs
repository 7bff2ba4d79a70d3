//! Validation of the `/frame` and `/gaussians` queries: every parameter is checked (known
//! name, given once, finite number, in range) before anything is rendered; an error is a
//! message naming the parameter, answered with status 400.

use seqavatar_evaluation::context_probe::ContextProbe;

use crate::orbit::OrbitView;

/// The smallest image side the viewer renders.
pub const MIN_SIDE: u32 = 16;
/// Elevations are kept this far (degrees) from the poles, where the look-at basis is undefined.
pub const MAX_ELEVATION_DEG: f64 = 89.0;
/// Bounds of the orbit distance (metres) and the field of view (degrees).
pub const DISTANCE_RANGE: (f64, f64) = (1e-3, 1e4);
pub const FOV_RANGE_DEG: (f64, f64) = (5.0, 150.0);
/// Pans beyond this many metres are refused.
pub const MAX_PAN: f64 = 1e4;
/// The longest tab id a page may send.
pub const MAX_TAB_LEN: usize = 64;

/// What the scene allows requests to name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Frames `first_frame..num_frames` can be drawn.
    pub first_frame: usize,
    pub num_frames: usize,
    pub num_cameras: usize,
    /// The largest image side (`--max-size`).
    pub max_side: u32,
}

/// Where a frame is seen from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum View {
    /// A dataset camera (index into the ingest entry's cameras), its image fitted into
    /// `max_width x max_height` (never enlarged).
    Dataset {
        camera: usize,
        max_width: u32,
        max_height: u32,
    },
    Orbit(OrbitView),
}

/// A validated `/frame` request.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRequest {
    /// The browser tab that asked: a newer request of the same tab replaces its pending one.
    pub tab: String,
    pub frame: usize,
    pub view: View,
    /// `None`: the avatar's own motion context.
    pub probe: Option<ContextProbe>,
    /// Also return the ground truth and the error map (dataset cameras only).
    pub compare: bool,
}

/// A validated `/gaussians` request: the posed Gaussians of frames `frame..frame + count`
/// ([`crate::stream`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GaussiansRequest {
    /// The browser tab that asked (as [`FrameRequest::tab`]).
    pub tab: String,
    pub frame: usize,
    /// Frames in the reply, `1..=`[`MAX_STREAM_FRAMES`].
    pub count: usize,
    pub probe: Option<ContextProbe>,
}

/// The most frames one `/gaussians` reply carries.
pub const MAX_STREAM_FRAMES: usize = 8;

/// Parses and validates the query pairs of `/gaussians`: `frame`, `count` (default 1; the
/// frames `frame..frame + count` must all be drawable), `context` and `tab` as for `/frame`.
pub fn parse_gaussians_request(
    pairs: &[(String, String)],
    limits: &Limits,
) -> Result<GaussiansRequest, String> {
    let get = known_pairs(pairs, &["tab", "frame", "count", "context"])?;
    let tab = parse_tab(&get)?;
    let frame = parse_frame(&get, limits)?;
    let count = get("count").map_or(Ok(1), |text| parse_index("count", text))?;
    if !(1..=MAX_STREAM_FRAMES).contains(&count) {
        return Err(format!(
            "`count` {count} is out of range 1..={MAX_STREAM_FRAMES}"
        ));
    }
    if frame + count > limits.num_frames {
        return Err(format!(
            "frames {frame}..={} reach past the last frame {}",
            frame + count - 1,
            limits.num_frames - 1
        ));
    }
    Ok(GaussiansRequest {
        tab,
        frame,
        count,
        probe: parse_probe(&get, limits)?,
    })
}

/// Checks that every name of `pairs` is in `known` and given once; returns the lookup of a
/// parameter's value.
fn known_pairs<'a>(
    pairs: &'a [(String, String)],
    known: &[&str],
) -> Result<impl Fn(&str) -> Option<&'a str>, String> {
    for (index, (name, _)) in pairs.iter().enumerate() {
        if !known.contains(&name.as_str()) {
            return Err(format!(
                "unknown parameter `{}` (known: {})",
                printable(name),
                known.join(", ")
            ));
        }
        if pairs[..index].iter().any(|(other, _)| other == name) {
            return Err(format!("parameter `{name}` is given more than once"));
        }
    }
    Ok(move |name: &str| {
        pairs
            .iter()
            .find(|(key, _)| key == name)
            .map(|(_, value)| value.as_str())
    })
}

/// The `tab` parameter, `default` when absent.
fn parse_tab<'a>(get: &impl Fn(&str) -> Option<&'a str>) -> Result<String, String> {
    let tab = get("tab").unwrap_or("default");
    if tab.is_empty()
        || tab.len() > MAX_TAB_LEN
        || !tab
            .bytes()
            .all(|byte| byte.is_ascii_alphanumeric() || byte == b'-' || byte == b'_')
    {
        return Err(format!(
            "`tab` must be 1 to {MAX_TAB_LEN} letters, digits, '-' or '_'"
        ));
    }
    Ok(tab.to_owned())
}

/// The required `frame` parameter, one of the drawable frames.
fn parse_frame<'a>(
    get: &impl Fn(&str) -> Option<&'a str>,
    limits: &Limits,
) -> Result<usize, String> {
    let frame_text = get("frame").ok_or("missing parameter `frame`")?;
    let frame = parse_index("frame", frame_text)?;
    if limits.first_frame >= limits.num_frames {
        return Err("the pose source has no frame that can be drawn".to_owned());
    }
    if frame < limits.first_frame || frame >= limits.num_frames {
        return Err(format!(
            "`frame` {frame} is out of range {}..={}{}",
            limits.first_frame,
            limits.num_frames - 1,
            if limits.first_frame > 0 {
                " (earlier frames have incomplete motion windows)"
            } else {
                ""
            }
        ));
    }
    Ok(frame)
}

/// The `context` parameter: `on` (default), `zeroed` or `from:OFFSET`.
fn parse_probe<'a>(
    get: &impl Fn(&str) -> Option<&'a str>,
    limits: &Limits,
) -> Result<Option<ContextProbe>, String> {
    Ok(match get("context").unwrap_or("on") {
        "on" => None,
        "zeroed" => Some(ContextProbe::Zeroed),
        other => {
            let offset_text = other.strip_prefix("from:").ok_or_else(|| {
                format!(
                    "`context` must be on, zeroed or from:OFFSET, not `{}`",
                    printable(other)
                )
            })?;
            let offset = parse_index("context offset", offset_text)?;
            let span = limits.num_frames - limits.first_frame;
            if offset == 0 || offset >= span {
                return Err(format!(
                    "`context` offset {offset} is out of range 1..={} (the drawable frames)",
                    span.saturating_sub(1)
                ));
            }
            Some(ContextProbe::FromFrame { offset })
        }
    })
}

/// Parses and validates the query pairs of `/frame`.
pub fn parse_frame_request(
    pairs: &[(String, String)],
    limits: &Limits,
) -> Result<FrameRequest, String> {
    let get = known_pairs(
        pairs,
        &[
            "tab", "frame", "camera", "az", "el", "dist", "fov", "px", "py", "w", "h", "context",
            "compare",
        ],
    )?;
    let tab = parse_tab(&get)?;
    let frame = parse_frame(&get, limits)?;
    let side = |name: &str| -> Result<Option<u32>, String> {
        get(name)
            .map(|text| {
                let value = parse_index(name, text)?;
                if value < MIN_SIDE as usize || value > limits.max_side as usize {
                    return Err(format!(
                        "`{name}` {value} is out of range {MIN_SIDE}..={}",
                        limits.max_side
                    ));
                }
                Ok(value as u32)
            })
            .transpose()
    };
    let (width, height) = (side("w")?, side("h")?);
    let orbit_names = ["az", "el", "dist", "fov", "px", "py"];
    let view = if let Some(text) = get("camera") {
        if let Some(name) = orbit_names.iter().find(|name| get(name).is_some()) {
            return Err(format!(
                "`camera` and the orbit parameter `{name}` exclude each other"
            ));
        }
        let camera = parse_index("camera", text)?;
        if camera >= limits.num_cameras {
            return Err(format!(
                "`camera` {camera} is out of range 0..={} ({} dataset cameras)",
                limits.num_cameras.saturating_sub(1),
                limits.num_cameras
            ));
        }
        View::Dataset {
            camera,
            max_width: width.unwrap_or(limits.max_side),
            max_height: height.unwrap_or(limits.max_side),
        }
    } else {
        let required = |name: &str| -> Result<f64, String> {
            let text = get(name).ok_or_else(|| {
                format!("missing parameter `{name}` (give `camera` or az, el, dist, w, h)")
            })?;
            parse_number(name, text)
        };
        let optional = |name: &str, default: f64| -> Result<f64, String> {
            get(name).map_or(Ok(default), |text| parse_number(name, text))
        };
        let azimuth_deg = required("az")?;
        let elevation_deg = required("el")?;
        let distance = required("dist")?;
        let fov_deg = optional("fov", 40.0)?;
        let (pan_right, pan_up) = (optional("px", 0.0)?, optional("py", 0.0)?);
        if elevation_deg.abs() > MAX_ELEVATION_DEG {
            return Err(format!(
                "`el` {elevation_deg} is out of range -{MAX_ELEVATION_DEG}..={MAX_ELEVATION_DEG} degrees"
            ));
        }
        if !(DISTANCE_RANGE.0..=DISTANCE_RANGE.1).contains(&distance) {
            return Err(format!(
                "`dist` {distance} is out of range {}..={} metres",
                DISTANCE_RANGE.0, DISTANCE_RANGE.1
            ));
        }
        if !(FOV_RANGE_DEG.0..=FOV_RANGE_DEG.1).contains(&fov_deg) {
            return Err(format!(
                "`fov` {fov_deg} is out of range {}..={} degrees",
                FOV_RANGE_DEG.0, FOV_RANGE_DEG.1
            ));
        }
        for (name, pan) in [("px", pan_right), ("py", pan_up)] {
            if pan.abs() > MAX_PAN {
                return Err(format!(
                    "`{name}` {pan} is out of range -{MAX_PAN}..={MAX_PAN} metres"
                ));
            }
        }
        let width = width.ok_or("missing parameter `w` (the image width)")?;
        let height = height.ok_or("missing parameter `h` (the image height)")?;
        View::Orbit(OrbitView {
            azimuth_deg: crate::orbit::wrap_degrees(azimuth_deg),
            elevation_deg,
            distance,
            fov_deg,
            pan_right,
            pan_up,
            width,
            height,
        })
    };
    let probe = parse_probe(&get, limits)?;
    let compare = match get("compare").unwrap_or("0") {
        "0" => false,
        "1" => true,
        other => {
            return Err(format!(
                "`compare` must be 0 or 1, not `{}`",
                printable(other)
            ));
        }
    };
    if compare && matches!(view, View::Orbit(_)) {
        return Err("`compare` needs a dataset `camera` (the ground truth is seen from it)".into());
    }
    Ok(FrameRequest {
        tab,
        frame,
        view,
        probe,
        compare,
    })
}

fn parse_index(name: &str, text: &str) -> Result<usize, String> {
    if text.is_empty() || text.len() > 9 || !text.bytes().all(|byte| byte.is_ascii_digit()) {
        return Err(format!(
            "`{name}` must be a non-negative integer, not `{}`",
            printable(text)
        ));
    }
    text.parse()
        .map_err(|_| format!("`{name}` must be a non-negative integer"))
}

fn parse_number(name: &str, text: &str) -> Result<f64, String> {
    if text.len() > 32 {
        return Err(format!("`{name}` is longer than 32 characters"));
    }
    let value: f64 = text
        .parse()
        .map_err(|_| format!("`{name}` must be a number, not `{}`", printable(text)))?;
    if !value.is_finite() {
        return Err(format!("`{name}` must be finite, not `{text}`"));
    }
    Ok(value)
}

/// At most 40 characters of `text`, control characters escaped, for error messages.
fn printable(text: &str) -> String {
    text.chars()
        .take(40)
        .flat_map(char::escape_default)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: Limits = Limits {
        first_frame: 2,
        num_frames: 10,
        num_cameras: 3,
        max_side: 512,
    };

    /// The pairs of `name=value&...` (not percent-decoded).
    fn pairs(query: &str) -> Vec<(String, String)> {
        query
            .split('&')
            .filter(|pair| !pair.is_empty())
            .map(|pair| {
                let (name, value) = pair.split_once('=').unwrap_or((pair, ""));
                (name.to_owned(), value.to_owned())
            })
            .collect()
    }

    fn parse(query: &str) -> Result<FrameRequest, String> {
        parse_frame_request(&pairs(query), &LIMITS)
    }

    #[test]
    fn valid_orbit_and_camera_requests() {
        let request =
            parse("tab=a-1&frame=2&az=-90&el=30&dist=2.5&w=256&h=16&context=zeroed").unwrap();
        assert_eq!(request.tab, "a-1");
        assert_eq!(request.frame, 2);
        assert_eq!(request.probe, Some(ContextProbe::Zeroed));
        let View::Orbit(orbit) = request.view else {
            panic!("{request:?}")
        };
        assert_eq!(orbit.azimuth_deg, 270.0);
        assert_eq!((orbit.width, orbit.height, orbit.fov_deg), (256, 16, 40.0));
        let request = parse("frame=9&camera=2&compare=1&context=from:7&w=100").unwrap();
        assert_eq!(
            request.view,
            View::Dataset {
                camera: 2,
                max_width: 100,
                max_height: 512
            }
        );
        assert_eq!(request.probe, Some(ContextProbe::FromFrame { offset: 7 }));
        assert!(request.compare);
        assert_eq!(request.tab, "default");
    }

    #[test]
    fn every_bad_parameter_is_named() {
        let base = "frame=3&az=0&el=0&dist=2&w=64&h=64";
        for (query, needle) in [
            ("", "missing parameter `frame`"),
            ("frame=1&camera=0", "`frame` 1 is out of range 2..=9"),
            ("frame=10&camera=0", "`frame` 10 is out of range"),
            (
                "frame=-1&camera=0",
                "`frame` must be a non-negative integer",
            ),
            ("frame=99999999999999999999&camera=0", "`frame` must be"),
            ("frame=3&camera=3", "`camera` 3 is out of range 0..=2"),
            ("frame=3&camera=0&az=1", "exclude each other"),
            ("frame=3&az=0&el=0&dist=2&w=64", "missing parameter `h`"),
            (
                "frame=3&az=NaN&el=0&dist=2&w=64&h=64",
                "`az` must be finite",
            ),
            (
                "frame=3&az=inf&el=0&dist=2&w=64&h=64",
                "`az` must be finite",
            ),
            (
                "frame=3&az=1e400&el=0&dist=2&w=64&h=64",
                "`az` must be finite",
            ),
            (
                "frame=3&az=x&el=0&dist=2&w=64&h=64",
                "`az` must be a number",
            ),
            (
                "frame=3&az=0&el=90&dist=2&w=64&h=64",
                "`el` 90 is out of range",
            ),
            (
                "frame=3&az=0&el=0&dist=0&w=64&h=64",
                "`dist` 0 is out of range",
            ),
            (
                "frame=3&az=0&el=0&dist=2&w=15&h=64",
                "`w` 15 is out of range 16..=512",
            ),
            (
                "frame=3&az=0&el=0&dist=2&w=64&h=513",
                "`h` 513 is out of range",
            ),
            (
                "frame=3&az=0&el=0&dist=2&w=64&h=64&fov=179",
                "`fov` 179 is out of range",
            ),
            (
                "frame=3&az=0&el=0&dist=2&w=64&h=64&px=1e5",
                "`px` 100000 is out of range",
            ),
            (
                "frame=3&camera=0&context=maybe",
                "`context` must be on, zeroed or from:OFFSET",
            ),
            (
                "frame=3&camera=0&context=from:0",
                "offset 0 is out of range 1..=7",
            ),
            (
                "frame=3&camera=0&context=from:8",
                "offset 8 is out of range",
            ),
            ("frame=3&camera=0&compare=yes", "`compare` must be 0 or 1"),
            (
                &format!("{base}&compare=1"),
                "`compare` needs a dataset `camera`",
            ),
            (
                &format!("{base}&frame=4"),
                "`frame` is given more than once",
            ),
            (
                &format!("{base}&path=/etc/passwd"),
                "unknown parameter `path`",
            ),
            (&format!("{base}&tab=../x"), "`tab` must be"),
            (&format!("{base}&tab="), "`tab` must be"),
        ] {
            let error = parse(query).expect_err(query);
            assert!(error.contains(needle), "{query}: {error}");
        }
    }

    fn parse_gaussians(query: &str) -> Result<GaussiansRequest, String> {
        parse_gaussians_request(&pairs(query), &LIMITS)
    }

    #[test]
    fn gaussian_requests_name_drawable_frame_ranges() {
        let request = parse_gaussians("frame=2&count=8&context=zeroed&tab=x").unwrap();
        assert_eq!((request.frame, request.count), (2, 8));
        assert_eq!(request.probe, Some(ContextProbe::Zeroed));
        assert_eq!(request.tab, "x");
        assert_eq!(parse_gaussians("frame=9").unwrap().count, 1);
        for (query, needle) in [
            ("", "missing parameter `frame`"),
            ("frame=1", "`frame` 1 is out of range 2..=9"),
            ("frame=10", "`frame` 10 is out of range"),
            (
                "frame=8&count=3",
                "frames 8..=10 reach past the last frame 9",
            ),
            ("frame=2&count=0", "`count` 0 is out of range 1..=8"),
            ("frame=2&count=9", "`count` 9 is out of range"),
            ("frame=2&count=-1", "`count` must be a non-negative integer"),
            ("frame=2&camera=0", "unknown parameter `camera`"),
            ("frame=2&frame=3", "given more than once"),
            ("frame=2&context=from:8", "offset 8 is out of range"),
            ("frame=2&tab=a/b", "`tab` must be"),
        ] {
            let error = parse_gaussians(query).expect_err(query);
            assert!(error.contains(needle), "{query}: {error}");
        }
    }

    #[test]
    fn a_source_without_drawable_frames_is_refused() {
        let limits = Limits {
            first_frame: 4,
            num_frames: 4,
            ..LIMITS
        };
        let pairs = vec![
            ("frame".to_owned(), "4".to_owned()),
            ("camera".to_owned(), "0".to_owned()),
        ];
        let error = parse_frame_request(&pairs, &limits).unwrap_err();
        assert!(error.contains("no frame that can be drawn"), "{error}");
    }
}
