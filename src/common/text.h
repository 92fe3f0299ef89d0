// Untrusted text: UTF-8 validation, nesting limits, and JSON parsing whose errors name the file.
//
// Every parser of a user's file (configs, adapter_config.json, safetensors headers, scene files,
// manifests) goes through these first, so that malformed bytes give one simu::Error naming the file
// and the position instead of a library exception, a stack overflow on absurd nesting, or a crash.
#pragma once

#include <nlohmann/json.hpp>

#include <cstddef>
#include <string>
#include <string_view>

namespace simu::text {

// Deepest nesting of [ { (outside JSON/YAML quoted strings) accepted by the parsers.
inline constexpr int kMaxNesting = 128;

// Byte offset of the first invalid UTF-8 sequence in s, or npos when s is valid UTF-8.
size_t find_invalid_utf8(std::string_view s);
// Throws simu::Error "<what>: invalid UTF-8 at line L, column C (byte 0xNN); <hint>" unless s is valid.
void check_utf8(std::string_view s, const std::string& what);
// Deepest nesting of brackets/braces outside quoted strings (a conservative count for JSON and for
// YAML flow collections).
int nesting_depth(std::string_view s);
// Parses JSON text with the checks above (UTF-8, nesting <= kMaxNesting); every failure is a
// simu::Error "<what>: not valid JSON: <position and reason>".
nlohmann::json parse_json(std::string_view s, const std::string& what);
// A JSON value as short text for messages (at most max_chars, "..." appended when cut).
std::string excerpt(const nlohmann::json& j, size_t max_chars = 80);

}  // namespace simu::text
