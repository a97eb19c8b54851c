// Filtered search: the `filter` search parameter (POST /v1/search, /v1/images/{id}/similar) and
// `oxbow query --filter`, a JSON object over the images' metadata documents (ImageRecord::
// metadata_json) that restricts which images a search may return (index::ImageFilter: applied while
// scoring, so the top-k are the best matches among the allowed images).
//
// Grammar (server/README.md, Filtered search):
//   filter    = { key: condition, ... }        every key must hold (AND); {} allows every image
//   condition = scalar                          equal: a string, number or boolean
//             | { op: operand, ... }            every operator must hold (AND), at least one
//   op        = "in"  (a non-empty array of at most kMaxFilterValues scalars: equal to one of them)
//             | "gt" | "gte" | "lt" | "lte"     (a number or a string; all bounds of one key the same type)
// Keys name top-level members of the metadata object, literally ("a.b" is the member called "a.b",
// not a path). An image matches a condition only when its metadata is an object holding the key with
// a value of the condition's type: numbers compare as numbers (2000 equals 2000.0), exactly: integers
// as integers (9007199254740993 is not 9007199254740992, which one double holds both as), an integer
// and a double by the double's exact value; a number written with a fraction or an exponent is the
// double nearest to it. Strings compare by their bytes (UTF-8, so by code point: ISO dates order
// correctly), booleans by equality; any other pairing (the number 2000 against the string "2000", an
// object or array value, null) does not match.
// Cost: an "in" list is a hash set built once when the filter is parsed, so matching one metadata
// document costs O(its size) whatever the number of values (at most kMaxFilterValues per "in", and
// kMaxFilterBytes of filter text in all).
// Thread-safe (pure functions; the filter is immutable).
#pragma once

#include <cstddef>
#include <memory>
#include <string_view>

#include "index/image_index.h"
#include "sift/base/error.h"

namespace oxbow::api {

inline constexpr size_t kMaxFilterBytes = 16 * 1024;  // filter text, checked before parsing
inline constexpr size_t kMaxFilterKeys = 64;          // keys of the filter object (a bit each when matching)
inline constexpr size_t kMaxFilterValues = 1000;      // operands of one "in"

// Parses and checks a filter (the grammar above); kInvalidArgument naming the problem and the value
// called `label` ("parameter 'filter'", "--filter"). `{}` gives null (no filter).
[[nodiscard]] Result<std::shared_ptr<const index::ImageFilter>> ParseFilter(std::string_view text,
                                                                            std::string_view label);

}  // namespace oxbow::api
